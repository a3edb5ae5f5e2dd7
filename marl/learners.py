"""The one registry of learning algorithms: every list of learners anywhere derives from it.

An entry names the algorithm, its family (which training loop trains it), where its config and
its training entry point live, the controller that acts with its checkpoints, whether it has one
network per follower, what it sends over V2V and a line for ``cacc-bench list``. This module
imports nothing heavy (no torch), so the controller registry and ``cacc-bench list`` read it
without loading a learner.

Families:

- ``a2c``: the paper's seven algorithms, one file each under ``marl/`` (its ``ALGORITHM`` record),
  trained by :mod:`marl.a2c` (one per-agent actor-critic per follower) and acted by
  :class:`controllers.policy.PolicyController`;
- ``ppo``: the acceleration-action learners of :mod:`marl.ppo` (one policy shared by every
  follower, or one per follower for ``ippo-bdc``), acted by
  :class:`controllers.shared_policy.SharedPolicyController`;
- ``distill``: the shared actor fitted to ``mpc`` by :mod:`marl.distill`, acted as the ``ppo``
  family's.
"""

from __future__ import annotations

from dataclasses import dataclass

#: The training families, in the order above.
LEARNER_FAMILIES: tuple[str, ...] = ("a2c", "ppo", "distill")

_PAPER_V2V = "see docs/spec/marl.md (neighbour blocks, messages)"
_ACCEL_V2V = "predecessor's command (1 float), leader's acceleration and speed (2 floats)"


@dataclass(frozen=True)
class LearnerSpec:
    """One learning algorithm.

    Attributes
    ----------
    name : str
        What ``--algo`` and ``--controllers`` take.
    family : str
        One of :data:`LEARNER_FAMILIES`: the loop that trains it.
    module : str
        The module that defines it (its config and networks; for the ``a2c`` family, its
        ``ALGORITHM`` record).
    acting : str
        ``module:Class`` of the controller that acts with its checkpoints.
    per_agent : bool
        One network per follower (it acts at its trained N only).
    v2v : str
        What its policy receives over V2V, in words.
    description : str
        One line for ``cacc-bench list``.
    """

    name: str
    family: str
    module: str
    acting: str
    per_agent: bool
    v2v: str
    description: str


def _paper(name: str) -> LearnerSpec:
    return LearnerSpec(
        name, "a2c", f"marl.{name}", "controllers.policy:PolicyController", True,
        _PAPER_V2V,
        f"trained {name} policy (shipped checkpoint; actions sampled, mode=greedy for argmax)")


def _ppo_shared(name: str, critic: str) -> LearnerSpec:
    return LearnerSpec(
        name, "ppo", "marl.ppo", "controllers.shared_policy:SharedPolicyController", False,
        f"accel mode: {_ACCEL_V2V}; ovm-gain mode: neighbour blocks",
        f"one policy shared by every follower (PPO, {critic}), any N; acceleration actions by "
        "default (shipped N = 8 checkpoint; actions sampled, mode=greedy for the mode)")


#: Every learning algorithm, by name, in the order ``cacc-bench list`` and the reports show them:
#: the paper's seven in its order, then the shared-policy learners.
LEARNERS: dict[str, LearnerSpec] = {s.name: s for s in (
    *(_paper(n) for n in ("ia2c", "fprint", "dial", "commnet", "wac", "dcea", "bdc")),
    _ppo_shared("ippo", "a critic of its own observation"),
    _ppo_shared("mappo", "a centralised critic (its observation and the platoon's mean)"),
    LearnerSpec(
        "distill", "distill", "marl.distill",
        "controllers.shared_policy:SharedPolicyController", False, _ACCEL_V2V,
        "the shared actor trained by imitation of mpc (behaviour cloning, then DAgger on "
        "training seeds), any N (shipped N = 8 checkpoint; actions sampled from the fitted "
        "Gaussian, mode=greedy for its mean)"),
    LearnerSpec(
        "ippo-bdc", "ppo", "marl.ppo",
        "controllers.shared_policy:SharedPolicyController", True,
        f"{_ACCEL_V2V}; in training, the critics' sign patterns to the front and rear neighbours",
        "BDC-MARL's consensus on the acceleration-action learner: an actor and critic per "
        "follower, critics agreeing by binary differential consensus, QSGD critic gradients "
        "(shipped N = 8 checkpoint, that N only; actions sampled, mode=greedy for the mode)"),
)}


def learners(*families: str) -> tuple[str, ...]:
    """Names of the learners of ``families`` (all of them without an argument), in registry
    order."""
    return tuple(n for n, s in LEARNERS.items() if not families or s.family in families)


#: The paper's algorithms, in its order (the ``a2c`` family).
PAPER_ALGORITHMS: tuple[str, ...] = learners("a2c")
#: The learners of :mod:`marl.ppo` (the ``ppo`` family).
PPO_LEARNERS: tuple[str, ...] = learners("ppo")
#: The learners that :class:`controllers.shared_policy.SharedPolicyController` acts for and the
#: shared-policy trainer trains (the ``ppo`` and ``distill`` families).
SHARED_LEARNERS: tuple[str, ...] = learners("ppo", "distill")
#: Those shared-policy learners with one network per follower (they act at their trained N).
PER_AGENT_SHARED: tuple[str, ...] = tuple(n for n in SHARED_LEARNERS if LEARNERS[n].per_agent)

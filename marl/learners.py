"""The one registry of learning algorithms: every list of learners anywhere derives from it.

An entry names the algorithm, its family (which training loop trains it), its config class, the
module that trains it, the class that acts with its checkpoints (every learned policy is the
one controller :class:`controllers.policy.PolicyController`; what differs is its acting class in
:mod:`marl.acting`), whether it has one network per follower, what it sends over V2V and a line
for ``cacc-bench list``. This module imports nothing heavy (no torch), so the controller
registry and ``cacc-bench list`` read it without loading a learner (:func:`load` imports what
an entry names, when it is needed).

Families:

- ``a2c``: the paper's seven algorithms, one file each under ``marl/`` (its ``ALGORITHM`` record),
  trained by :mod:`marl.a2c` (one per-agent actor-critic per follower), acting through
  :class:`marl.acting.PaperActing`;
- ``ppo``: the acceleration-action learners of :mod:`marl.ppo` (one policy shared by every
  follower), and :mod:`marl.ippo_bdc` (one per follower, its update overridden), acting
  through :class:`marl.acting.SharedActing`;
- ``distill``: the shared actor fitted to ``mpc`` by :mod:`marl.distill`, acting as the ``ppo``
  family's.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from typing import Any

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
    config : str
        ``module:Class`` of its config (the fields ``--set`` takes).
    module : str
        The module that trains it (for the ``a2c`` family, its ``ALGORITHM`` record; for the
        ``ppo`` family, its ``TRAINER`` class).
    acting : str
        ``module:Class`` of the acting class (:mod:`marl.acting`) the one policy controller
        acts with its checkpoints through.
    per_agent : bool
        One network per follower (it acts at its trained N only).
    v2v : str
        What its policy receives over V2V, in words.
    description : str
        One line for ``cacc-bench list``.
    """

    name: str
    family: str
    config: str
    module: str
    acting: str
    per_agent: bool
    v2v: str
    description: str


def _paper(name: str, config: str) -> LearnerSpec:
    return LearnerSpec(
        name, "a2c", f"marl.{name}:{config}", f"marl.{name}", "marl.acting:PaperActing", True,
        _PAPER_V2V,
        f"trained {name} policy (shipped checkpoint; actions sampled, mode=greedy for argmax)")


_PPO_CONFIG = "marl.ppo_nets:PPOConfig"
_SHARED_ACTING = "marl.acting:SharedActing"


def _ppo_shared(name: str, critic: str) -> LearnerSpec:
    return LearnerSpec(
        name, "ppo", _PPO_CONFIG, "marl.ppo", _SHARED_ACTING, False,
        f"accel mode: {_ACCEL_V2V}; ovm-gain mode: neighbour blocks",
        f"one policy shared by every follower (PPO, {critic}), any N; acceleration actions by "
        "default (shipped N = 8 checkpoint; actions sampled, mode=greedy for the mode)")


#: Every learning algorithm, by name, in the order ``cacc-bench list`` and the reports show them:
#: the paper's seven in its order, then the shared-policy learners.
LEARNERS: dict[str, LearnerSpec] = {s.name: s for s in (
    *(_paper(n, c) for n, c in (("ia2c", "IA2CConfig"), ("fprint", "FPrintConfig"),
                                ("dial", "DIALConfig"), ("commnet", "CommNetConfig"),
                                ("wac", "WACConfig"), ("dcea", "DCEAConfig"),
                                ("bdc", "BDCConfig"))),
    _ppo_shared("ippo", "a critic of its own observation"),
    _ppo_shared("mappo", "a centralised critic (its observation and the platoon's mean)"),
    LearnerSpec(
        "distill", "distill", "marl.distill:DistillConfig", "marl.distill", _SHARED_ACTING,
        False, _ACCEL_V2V,
        "the shared actor trained by imitation of mpc (behaviour cloning, then DAgger on "
        "training seeds), any N (shipped N = 8 checkpoint; actions sampled from the fitted "
        "Gaussian, mode=greedy for its mean)"),
    LearnerSpec(
        "ippo-bdc", "ppo", _PPO_CONFIG, "marl.ippo_bdc", _SHARED_ACTING, True,
        f"{_ACCEL_V2V}; in training, the critics' sign patterns to the front and rear neighbours",
        "BDC-MARL's consensus on the acceleration-action learner: an actor and critic per "
        "follower, critics agreeing by binary differential consensus, QSGD critic gradients "
        "(shipped N = 8 checkpoint, that N only; actions sampled, mode=greedy for the mode)"),
    LearnerSpec(
        "ippo-gains", "ppo", "marl.ippo_gains:GainScheduleConfig", "marl.ippo_gains",
        "marl.ippo_gains:GainActing", False, _ACCEL_V2V,
        "one policy shared by every follower (PPO) that schedules cacc's gains and time gap "
        "along a segment certified string stable, any N (shipped N = 8 checkpoint; actions "
        "sampled, mode=greedy for the mode)"),
)}


def learners(*families: str) -> tuple[str, ...]:
    """Names of the learners of ``families`` (all of them without an argument), in registry
    order."""
    return tuple(n for n, s in LEARNERS.items() if not families or s.family in families)


#: The paper's algorithms, in its order (the ``a2c`` family).
PAPER_ALGORITHMS: tuple[str, ...] = learners("a2c")
#: The learners of :mod:`marl.ppo` (the ``ppo`` family).
PPO_LEARNERS: tuple[str, ...] = learners("ppo")
#: The shared-policy learners (the ``ppo`` and ``distill`` families).
SHARED_LEARNERS: tuple[str, ...] = learners("ppo", "distill")
#: Those shared-policy learners with one network per follower (they act at their trained N).
PER_AGENT_SHARED: tuple[str, ...] = tuple(n for n in SHARED_LEARNERS if LEARNERS[n].per_agent)


def load(ref: str) -> Any:
    """What a ``module:Name`` reference of an entry names (imports the module)."""
    module, _, name = ref.partition(":")
    return getattr(importlib.import_module(module), name)

"""Trained policies as controllers: one controller for every learner of :mod:`marl.learners`.

``PolicyController(algo)`` loads ``controllers/checkpoints/<algo>__<scenario>__n<N>__s<seed>.pt``
for the run's scenario at :meth:`reset` and picks each follower's action every step: drawn from
the policy (``mode=sampled``, the default: the policy as trained) or its mode (``mode=greedy``).
The paper's per-agent policies load the checkpoint of the run's N; a shared learner's one
checkpoint (trained with ``vehicles`` followers, 8 by default) drives any N from 2 to 64. How a
network acts, and what it sends, is its acting class's (:mod:`marl.acting`); this module keeps
the closed loop's part. Sampled actions use the uniforms of the acting class's stream of
:func:`envs.streams.episode_uniforms`, a pure function of the episode seed, the agent and the
step: reruns, batches and every executor give the same actions, and every policy of a family
draws the same numbers (common random numbers across algorithms). Every message goes through
channels of the episode context, so delay and loss act on it and its bits are counted.
"""

from __future__ import annotations

import functools
import inspect
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from controllers.base import Controller, EpisodeContext, Message
from envs.params import EVAL_MODES
from envs.platoon import PlatoonState
from envs.scenarios import make_scenario
from envs.streams import episode_uniforms
from infra.errors import ConfigError
from infra.limits import MAX_TRAIN_SEED, check_seeds
from infra.naming import checkpoint_stem, coerce_option
from marl.learners import LEARNERS

CHECKPOINT_DIR = Path(__file__).resolve().parent / "checkpoints"
#: Steps of action uniforms drawn at once (the draws do not depend on it; memory B N 8 bytes each)
UNIFORM_BLOCK_STEPS = 64
#: Shipped policies trained with another config than the leaderboard's (one folder each).
VARIANT_DIR = CHECKPOINT_DIR / "variants"
#: Shipped variants of ``ippo`` (``ippo:variant=NAME``): a residual on ``cacc``, the same with a
#: time-aware critic, and the published OVM-gain action set.
IPPO_VARIANTS: tuple[str, ...] = ("residual-cacc", "residual-timed", "ovm-gain")
#: Fewest episodes' rows a policy network is evaluated on (see :meth:`PolicyController.reset`):
#: float32 products of 1 row (gemv), and of 2 or 3 rows on AMD EPYC with this torch build's
#: AVX-512 kernels, round otherwise than the rows of a larger batch, and so do ``ippo-bdc``'s
#: batched products ``(N, M, D) @ (N, D, H)`` of 1 to 6 rows; with 8, measured equal for all.
MIN_LANES = 8


@dataclass(frozen=True)
class Declared:
    """What the policies of a learner family declare to the harness (see
    :class:`controllers.base.Controller`), and their one option beside the common ones."""

    option: str
    drives_mixed: bool
    needs_leader: bool
    needs_observation: bool


#: By learner family: the paper's per-agent policies were trained on homogeneous strings behind a
#: leader and read the env's observation (``untrained``: fresh weights); a shared policy sees
#: only what an automated vehicle senses or receives (behind a human, nothing: its command reads
#: as the 0 held before any message; on a ring the leader's broadcast never arrives and
#: follower 1 hears follower N) and acts at any N (``vehicles``: the N it was trained with).
DECLARED: dict[str, Declared] = {"a2c": Declared("untrained", False, True, True),
                                 "ppo": Declared("vehicles", True, False, False),
                                 "distill": Declared("vehicles", True, False, False)}


def declared(algo: str) -> Declared:
    """What the policy of the learner ``algo`` declares; an unknown name is a ConfigError."""
    if algo not in LEARNERS:
        raise ConfigError(f"unknown learned policy {algo!r}; valid: {', '.join(LEARNERS)}")
    return DECLARED[LEARNERS[algo].family]


@functools.cache
def rows_are_batch_invariant(algo: str) -> bool:
    """Whether this machine's kernels give a row of ``algo``'s network the same numbers among
    64 rows as among :data:`MIN_LANES` (:meth:`marl.acting.Acting.probe`: random weights and
    inputs, once per process and algorithm). Measured true on the machines this project runs
    on; where it is false the harness runs policy episodes one at a time instead of batching
    them (still exact)."""
    import torch

    from marl.acting import PROBE_ROWS, acting

    probe = acting(algo).probe
    full = probe(algo, list(range(PROBE_ROWS)))
    return all(torch.equal(lone[0], batched[row]) for row in (0, 31, PROBE_ROWS - 1)
               for lone, batched in zip(probe(algo, [row] * MIN_LANES), full, strict=True))


def shipped_variants(algo: str | None = None) -> list[str]:
    """Names of the shipped checkpoint variants (folders of ``VARIANT_DIR``), sorted; with
    ``algo``, those holding a checkpoint of it."""
    if not VARIANT_DIR.is_dir():
        return []
    return sorted(p.name for p in VARIANT_DIR.iterdir() if p.is_dir()
                  and (algo is None or any(p.glob(f"{algo}__*.pt"))))


def checkpoint_path(
    algo: str, scenario: str, n_vehicles: int, seed: int = 0, folder: str | Path | None = None
) -> Path:
    """Where the checkpoint of a run lives: the shipped one, or the one in ``folder``."""
    base = CHECKPOINT_DIR if folder is None else Path(folder)
    return base / f"{checkpoint_stem(algo, scenario, n_vehicles, seed)}.pt"


class PolicyController(Controller):
    """The policy of a trained learner, sampled (default) or greedy.

    Parameters
    ----------
    algo : str
        A learner of :data:`marl.learners.LEARNERS` (``ia2c`` ... ``bdc``, ``ippo``, ``mappo``,
        ``distill``, ``ippo-bdc``).
    scenario : str, optional
        Load the checkpoint trained on this scenario instead of the run's one.
    checkpoint : str or Path, optional
        Explicit checkpoint file: the policy is what the file records (its scenario, N and
        seed), so ``scenario``, ``seed``, ``checkpoint_dir`` and ``variant`` are not given with
        it.
    checkpoint_dir : str or Path, optional
        Folder to load ``<algo>__<scenario>__n<N>__s<seed>.pt`` from instead of the shipped
        checkpoints (a ``cacc-bench train --out`` or ``cacc-bench reproduce`` folder); unlike
        ``checkpoint``, the training seeds of one folder pool into one leaderboard row.
    seed : int
        Training seed of the checkpoint (0).
    vehicles : int
        Shared learners: N the checkpoint was trained with (8); the run's N may differ
        (``ippo-bdc``, one network per follower: not).
    variant : str, optional
        A shipped variant trained with another config (a folder of
        ``controllers/checkpoints/variants``, e.g. ``w5_m1``: the power weight w5 = -1 of
        ``cacc-bench pareto``; ``ovm-gain``: ``ippo`` in the published action mode); see
        :func:`shipped_variants`.
    untrained : bool
        The paper's learners: act with freshly initialised weights (the "untrained policy"
        reference; no file read).
    mode : {"sampled", "greedy"}
        ``sampled`` (default): actions drawn from the policy, as trained, from the episode's
        own stream (reproducible). ``greedy``: the mode (the argmax action, the Gaussian's mean).
    """

    family = "marl"
    deterministic = False

    def __init__(
        self,
        algo: str,
        scenario: str | None = None,
        checkpoint: Path | str | None = None,
        checkpoint_dir: Path | str | None = None,
        seed: int | str = 0,
        vehicles: int | str = 8,
        variant: str | None = None,
        untrained: bool | str = False,
        mode: str = "sampled",
        **options: Any,
    ) -> None:
        super().__init__()
        decl = declared(algo)
        known = self.options_of(algo)
        for key, value, default in (("vehicles", vehicles, 8), ("untrained", untrained, False)):
            if key not in known and value != default:  # the other family's option
                options[key] = value
        if options:
            raise ConfigError(f"{algo} has no option(s) {sorted(options)}; its options are: "
                              f"{', '.join(sorted(known))}")
        if mode not in EVAL_MODES:
            raise ConfigError(f"{algo}: mode must be one of {', '.join(EVAL_MODES)}, got {mode!r}")
        seed = int(coerce_option(seed, int, "seed", algo))  # the one rule for option values
        for key, path in (("checkpoint", checkpoint), ("checkpoint_dir", checkpoint_dir)):
            if path is not None:
                coerce_option(str(path), Path, key, algo)  # an empty one is refused
        if checkpoint is not None:
            naming = [k for k, v in (("scenario", scenario), ("seed", seed or None),
                                     ("checkpoint_dir", checkpoint_dir), ("variant", variant))
                      if v is not None]
            if naming:
                raise ConfigError(
                    f"{algo}: checkpoint=FILE names one policy, the one the file records (its "
                    f"scenario, N and seed); leave out {', '.join(naming)}, or drop checkpoint= "
                    "to pick a file by scenario and seed")
        check_seeds([seed], f"{algo}: seed", MAX_TRAIN_SEED)  # what `train` can make
        self.vehicles = (int(coerce_option(vehicles, int, "vehicles", algo))
                         if "vehicles" in known else None)
        if self.vehicles is not None and not 2 <= self.vehicles <= 64:
            raise ConfigError(f"{algo}: vehicles must lie in 2..64, got {self.vehicles}")
        if variant is not None:
            if checkpoint_dir is not None:
                raise ConfigError(f"{algo}: give variant or checkpoint_dir, not both")
            if variant not in shipped_variants():  # the list: those holding this algorithm
                raise ConfigError(f"{algo}: unknown variant {variant!r}; shipped with {algo}: "
                                  f"{', '.join(shipped_variants(algo)) or 'none'}")
        self.name = self.algo = algo
        self.drives_mixed, self.needs_leader = decl.drives_mixed, decl.needs_leader
        self.needs_observation = decl.needs_observation
        self.scenario, self.checkpoint, self.checkpoint_dir = scenario, checkpoint, checkpoint_dir
        self.seed, self.variant, self.mode = seed, variant, mode
        self.deterministic = mode == "greedy"
        self.untrained = "untrained" in known and bool(
            coerce_option(untrained, bool, "untrained", algo))
        self.options = {k: v for k, v in {
            "scenario": scenario, "checkpoint": checkpoint, "checkpoint_dir": checkpoint_dir,
            "seed": seed or None, "vehicles": self.vehicles if self.vehicles != 8 else None,
            "variant": variant, "untrained": self.untrained or None,
            "mode": mode if mode != EVAL_MODES[0] else None}.items() if v is not None}
        self.policy: Any = None  # the marl.acting.Acting acting now, loaded for self._key
        self.loaded: dict[str, Any] = {}
        self._key: tuple[str, int] | None = None

    @classmethod
    def options_of(cls, algo: str) -> dict[str, Any]:
        """The options of ``algo``'s policy with their defaults: the common ones and its
        family's own (:data:`DECLARED`), in the order ``cacc-bench list`` shows them."""
        others = {d.option for d in DECLARED.values()} - {declared(algo).option}
        return {p.name: p.default for p in inspect.signature(cls).parameters.values()
                if p.default is not p.empty and p.name not in others}

    #: What ``algo``'s policy declares, without building it (the registry's lists).
    traits = staticmethod(declared)

    @property
    def batch_invariant(self) -> bool:  # type: ignore[override]
        """Batched episodes equal lone ones where the probe says rows do not depend on the batch
        (:func:`rows_are_batch_invariant`, run when first asked, then cached per algorithm)."""
        return rows_are_batch_invariant(self.algo)

    @staticmethod
    def batch_invariant_probe(algo: str, **_: Any) -> bool:
        """Whether the harness may batch this algorithm's episodes here
        (:func:`rows_are_batch_invariant`)."""
        return rows_are_batch_invariant(algo)

    @property
    def net(self) -> Any:
        """The network acting now (None before the first load)."""
        return None if self.policy is None else self.policy.net

    @classmethod
    def from_net(
        cls, algo: str, net: Any, scenario_id: str, n_vehicles: int, mode: str = "sampled"
    ) -> PolicyController:
        """A controller acting with an in-memory network (training's validation: the same
        closed loop as the benchmark, on the weights being trained)."""
        from marl.acting import acting

        ctrl = cls(algo, mode=mode)
        ctrl.policy = acting(algo)(algo, net)
        ctrl._key = ctrl._source(scenario_id, n_vehicles)
        ctrl.loaded = {"scenario": scenario_id}
        return ctrl

    # ---------------------------------------------------------------- loading
    def _source(self, scenario_id: str, n_vehicles: int) -> tuple[str, int]:
        """The scenario and N of the checkpoint a run on ``scenario_id`` with N followers acts
        with."""
        return self.scenario or scenario_id, self.vehicles or n_vehicles

    def _load(self, source: str, n: int) -> Any:
        """The policy of the checkpoint trained on ``source`` with ``n`` followers."""
        import torch

        from marl.acting import PaperActing, acting, untrained_net
        from marl.checkpoint import load_checkpoint, policy_id, train_command

        torch.set_num_threads(1)
        if self.untrained:
            self.loaded, self._policy_sha256 = {"steps": 0, "scenario": source}, ""
            return PaperActing(self.algo, untrained_net(self.algo, n, self.seed))
        folder = VARIANT_DIR / self.variant if self.variant else self.checkpoint_dir
        path = (Path(self.checkpoint) if self.checkpoint is not None
                else checkpoint_path(self.algo, source, n, self.seed, folder))
        if not path.exists() and self.variant:
            have = sorted(f.name for f in (VARIANT_DIR / self.variant).glob("*.pt"))
            raise ConfigError(
                f"variant {self.variant!r} has no {self.algo} policy for {source} with "
                f"N = {n} ({path.name} missing); it holds: {', '.join(have) or 'nothing'}")
        if not path.exists():
            make_scenario(source)  # an unknown scenario id is named as such, not to be trained on
            cmd = train_command(self.algo, source, n, self.seed, str(folder or CHECKPOINT_DIR))
            raise ConfigError(
                f"no trained {self.algo} policy for {source} with N = {n}: {path} is missing; "
                f"make it with `{cmd}` (or pick another checkpoint with {self.algo}:scenario=ID "
                "or checkpoint=FILE)")
        data = load_checkpoint(path, **self._identity(source, n))
        self.loaded, self._policy_sha256 = data, policy_id(data)
        return acting(self.algo).load(self.algo, data)

    def _identity(self, source: str, n: int) -> dict[str, Any]:
        """What the checkpoint loaded for ``source`` and N = ``n`` must record
        (:func:`marl.checkpoint.load_checkpoint` refuses another): a file found by its name holds
        the algorithm, scenario, N and seed of that name, whatever was copied or renamed there;
        an explicit ``checkpoint=FILE`` is the policy it records, of this algorithm (the paper's
        learners: at the run's N; a shared one acts at any N)."""
        if self.checkpoint is None:
            return {"algo": self.algo, "scenario": source, "n_vehicles": n, "seed": self.seed}
        return {"algo": self.algo, "n_vehicles": None if self.vehicles else n}

    def preflight(self, scenario: Any, n_vehicles: int, params: Any = None) -> None:
        """Load the policy for ``scenario`` and N now, so a missing or mismatched checkpoint
        fails before a sweep starts (a clear error, nothing stored). The paper's per-agent
        policies (trained on the homogeneous string of i3-class cars) are refused on a string
        of vehicle classes (the scenario option ``classes`` or ``class_mix``)."""
        if not self.drives_mixed and scenario.vehicle_classes(n_vehicles) is not None:
            shared = ", ".join(n for n in LEARNERS if declared(n).drives_mixed)
            raise ConfigError(
                f"{self.algo} cannot run on {scenario.label or scenario.id}: its policies were "
                "trained on the homogeneous string of one car and know nothing of other "
                "vehicles' lags and bounds; on a string of vehicle classes run the linear laws "
                f"(acc, cacc), the distributed MPC (mpc, mpc-qp), the human models, or the "
                f"shared policies ({shared})")
        key = self._source(scenario.id, n_vehicles)
        if self.policy is None or self._key != key:
            self.policy, self._key = self._load(*key), key
        self.policy.check_vehicles(n_vehicles)

    # ---------------------------------------------------------------- interface
    def messages(self, ctx: EpisodeContext) -> tuple[Message, ...]:
        """What the policy's acting class sends (:meth:`marl.acting.Acting.messages`)."""
        self.preflight(ctx.scenario, ctx.n_vehicles)
        return tuple(Message(*m) for m in self.policy.messages(ctx.n_vehicles))

    def reset(self, ctx: EpisodeContext) -> None:
        self.preflight(ctx.scenario, ctx.n_vehicles)
        # at least MIN_LANES lanes: a matrix product of fewer rows takes other kernels whose
        # rounding differs from the rows of a batch; with >= MIN_LANES rows each row's numbers
        # do not depend on the batch, so an episode acts the same alone or batched (tested)
        self._lanes = max(ctx.batch_size, MIN_LANES)
        self.seeds, self.t, self._n = ctx.seeds, 0, ctx.n_vehicles
        self._u_block: np.ndarray | None = None
        self._u_start = 0
        self.policy.reset(ctx, self._lanes)

    def _uniforms(self) -> np.ndarray:
        """This step's action uniforms ``(B, N)``, drawn :data:`UNIFORM_BLOCK_STEPS` steps at a
        time (the same numbers as one draw per step, in one vectorised pass)."""
        k = self.t - self._u_start
        if self._u_block is None or k >= len(self._u_block):
            self._u_block = episode_uniforms(self.seeds, self.policy.stream, self.t, self._n,
                                             steps=UNIFORM_BLOCK_STEPS)
            self._u_start, k = self.t, 0
        return self._u_block[k]

    def act(self, state: PlatoonState, observation: np.ndarray | None) -> np.ndarray:
        from marl.acting import pad_rows

        uniforms = pad_rows(self._uniforms(), self._lanes) if self.mode == "sampled" else None
        self.t += 1
        return self.policy.act(state, observation, uniforms)

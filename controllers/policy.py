"""Trained MARL policies as controllers (actions of a shipped checkpoint's policy).

``PolicyController(algo)`` loads ``controllers/checkpoints/<algo>__<scenario>__n<N>__s<seed>.pt``
for the run's scenario and N at :meth:`reset`, keeps every agent's recurrent state, and picks
each follower's action every step: drawn from the policy (``mode=sampled``, the default: the
policy as trained) or its argmax (``mode=greedy``). The action becomes the OVM command of the
published action table. Sampled actions use the uniforms of the stream ``policy-actions`` of
:func:`envs.streams.episode_uniforms`, a pure function of the episode seed, the agent and the
step: reruns, batches and every executor give the same actions, and every policy of a run draws
the same numbers (common random numbers across algorithms). Every message goes through channels of the episode context, so delay and loss act
on it and its bits are counted: each follower's 5-float vehicle block to its front and rear
neighbours (the observation's neighbour blocks are rebuilt from what arrived), and, for FPrint,
DIAL and CommNet, the algorithm's message (4 or 64 floats) likewise.
"""

from __future__ import annotations

import functools
from pathlib import Path
from typing import Any

import numpy as np

from controllers.base import Controller, EpisodeContext, Message
from envs.dynamics import OBS_DIM, action_to_command_mps2
from envs.params import EVAL_MODES
from envs.platoon import PlatoonState
from envs.scenarios import make_scenario
from envs.streams import episode_uniforms
from infra.errors import ConfigError
from infra.limits import MAX_TRAIN_SEED, check_seeds
from infra.naming import checkpoint_stem, coerce_option

CHECKPOINT_DIR = Path(__file__).resolve().parent / "checkpoints"
#: Name of the per-episode uniform stream sampled actions are drawn from.
ACTION_STREAM = "policy-actions"
#: Steps of action uniforms drawn at once (the draws do not depend on it; memory B N 8 bytes each)
UNIFORM_BLOCK_STEPS = 64
#: Shipped policies trained with another config than the leaderboard's (one folder each).
VARIANT_DIR = CHECKPOINT_DIR / "variants"
#: Fewest rows the policy network is evaluated on (see :meth:`PolicyController.reset`): float32
#: products of 1 row (gemv), and of 2 or 3 rows on AMD EPYC with this torch build's AVX-512
#: kernels, round otherwise than the rows of a larger batch; from 4 rows on, measured equal.
MIN_LANES = 4


@functools.cache
def rows_are_batch_invariant(algo: str, n_agents: int = 8) -> bool:
    """Whether this machine's kernels give a row of ``algo``'s network the same numbers among
    64 rows as among :data:`MIN_LANES` (a probe on random weights and inputs, once per process
    and algorithm). Measured true on the machines this project runs on; where it is false the
    harness runs policy episodes one at a time instead of batching them (still exact)."""
    import torch

    from marl.acting import algorithm, exchange

    spec = algorithm(algo)
    with torch.no_grad():
        net = spec.build_net(spec.config_cls(), n_agents, with_critic=False,
                             generator=torch.Generator().manual_seed(0))
        gen = torch.Generator().manual_seed(1)
        obs = torch.randn(n_agents, 64, OBS_DIM, generator=gen)
        state = {k: torch.randn(v.shape, generator=gen) for k, v in net.initial_state(64).items()}
        logits, _, new = net.act_step(obs, state, *exchange(net, state))
        for row in (0, 31, 63):
            rows = [row] * MIN_LANES
            sub = {k: v[:, rows].contiguous() for k, v in state.items()}
            lg, _, nw = net.act_step(obs[:, rows].contiguous(), sub, *exchange(net, sub))
            if not torch.equal(lg[:, 0], logits[:, row]) or not all(
                    torch.equal(nw[k][:, 0], new[k][:, row]) for k in new):
                return False
    return True


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
    """The policy of a trained MARL algorithm, sampled (default) or greedy.

    Parameters
    ----------
    algo : str
        Algorithm name (``ia2c``, ``fprint``, ``dial``, ``commnet``, ``wac``, ``dcea``, ``bdc``).
    scenario : str, optional
        Load the checkpoint trained on this scenario instead of the run's one.
    checkpoint : str, optional
        Explicit checkpoint file (overrides ``scenario``).
    checkpoint_dir : str, optional
        Folder to load ``<algo>__<scenario>__n<N>__s<seed>.pt`` from instead of the shipped
        checkpoints (a ``cacc-bench train --out`` or ``cacc-bench reproduce`` folder); unlike
        ``checkpoint``, the training seeds of one folder pool into one leaderboard row.
    seed : int
        Training seed of the shipped checkpoint (0).
    variant : str, optional
        A shipped variant trained with another config (a folder of
        ``controllers/checkpoints/variants``, e.g. ``w5_m1``: the power weight w5 = -1 of
        ``cacc-bench pareto``); see :func:`shipped_variants`.
    untrained : bool
        Act with freshly initialised weights (the "untrained policy" reference; no file read).
    mode : {"sampled", "greedy"}
        ``sampled`` (default): actions drawn from the policy, as trained, from the episode's
        own stream (reproducible). ``greedy``: the argmax action.
    """

    family = "marl"
    #: the paper's per-agent policies were trained on homogeneous strings behind a leader
    drives_mixed = False
    needs_leader = True
    deterministic = False
    needs_observation = True

    def __init__(
        self,
        algo: str,
        scenario: str | None = None,
        checkpoint: str | None = None,
        checkpoint_dir: str | None = None,
        seed: int | str = 0,
        variant: str | None = None,
        untrained: bool | str = False,
        mode: str = "sampled",
        **options: Any,
    ) -> None:
        super().__init__()
        from marl.learners import PAPER_ALGORITHMS

        if options:
            raise ConfigError(
                f"{algo} has no option(s) {sorted(options)}; its options are: checkpoint, "
                "checkpoint_dir, mode, scenario, seed, untrained, variant"
            )
        if mode not in EVAL_MODES:
            raise ConfigError(f"{algo}: mode must be one of {', '.join(EVAL_MODES)}, got {mode!r}")
        seed = int(coerce_option(seed, int, "seed", algo))  # the one rule for option values
        check_seeds([seed], f"{algo}: seed", MAX_TRAIN_SEED)  # what `train` can make
        if algo not in PAPER_ALGORITHMS:
            raise ConfigError(
                f"unknown MARL algorithm {algo!r}; valid: {', '.join(PAPER_ALGORITHMS)}"
            )
        if variant is not None:
            if checkpoint_dir is not None:
                raise ConfigError(f"{algo}: give variant or checkpoint_dir, not both")
            if variant not in shipped_variants():  # the list: those holding this algorithm
                raise ConfigError(
                    f"{algo}: unknown variant {variant!r}; shipped with {algo}: "
                    f"{', '.join(shipped_variants(algo)) or 'none'}"
                )
        self.variant = variant
        self.algo = algo
        self.name = algo
        self.scenario = scenario
        self.checkpoint = checkpoint
        self.checkpoint_dir = checkpoint_dir
        self.seed = seed
        self.mode = mode
        self.deterministic = mode == "greedy"
        self.untrained = bool(coerce_option(untrained, bool, "untrained", algo))
        self.options = {
            k: v
            for k, v in {
                "scenario": scenario,
                "checkpoint": checkpoint,
                "checkpoint_dir": checkpoint_dir,
                "seed": seed if seed else None,
                "variant": variant,
                "untrained": True if self.untrained else None,
                "mode": mode if mode != EVAL_MODES[0] else None,
            }.items()
            if v is not None
        }
        self.net: Any = None
        self.loaded: dict[str, Any] = {}

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

    @classmethod
    def from_net(
        cls, algo: str, net: Any, scenario_id: str, n_vehicles: int, mode: str = "sampled"
    ) -> PolicyController:
        """A controller acting with an in-memory network (training's validation: the same
        closed loop as the benchmark, on the weights being trained)."""
        ctrl = cls(algo, mode=mode)
        ctrl.net = net
        ctrl._key = (scenario_id, n_vehicles)
        ctrl.loaded = {"scenario": scenario_id}
        return ctrl

    # ---------------------------------------------------------------- loading
    def _load(self, scenario_id: str, n_vehicles: int) -> Any:
        import torch

        from marl.acting import acting_net, untrained_net
        from marl.checkpoint import load_checkpoint, policy_id, train_command

        torch.set_num_threads(1)
        if self.untrained:
            self.loaded = {"steps": 0, "scenario": scenario_id}
            self._policy_sha256 = ""
            return untrained_net(self.algo, n_vehicles, self.seed)
        source = self.scenario or scenario_id
        folder = VARIANT_DIR / self.variant if self.variant else self.checkpoint_dir
        path = (
            Path(self.checkpoint)
            if self.checkpoint
            else checkpoint_path(self.algo, source, n_vehicles, self.seed, folder)
        )
        if not path.exists() and self.variant:
            have = sorted(f.name for f in (VARIANT_DIR / self.variant).glob("*.pt"))
            raise ConfigError(
                f"variant {self.variant!r} has no {self.algo} policy for {source} with "
                f"N = {n_vehicles} ({path.name} missing); it holds: {', '.join(have) or 'nothing'}"
            )
        if not path.exists():
            make_scenario(source)  # an unknown scenario id is named as such, not to be trained on
            cmd = train_command(self.algo, source, n_vehicles, self.seed, self.checkpoint_dir or "")
            raise ConfigError(
                f"no trained {self.algo} policy for {source} with N = {n_vehicles}: {path} is "
                f"missing; make it with `{cmd}`"
                f" (or pick another checkpoint with {self.algo}:scenario=ID or checkpoint=FILE)"
            )
        data = load_checkpoint(path, algo=self.algo, n_vehicles=n_vehicles, scenario=source)
        net = acting_net(self.algo, n_vehicles, data)
        self.loaded, self._policy_sha256 = data, policy_id(data)
        return net

    def preflight(self, scenario: Any, n_vehicles: int, params: Any = None) -> None:
        """Load the policy for ``scenario`` and N now, so a missing or mismatched checkpoint
        fails before a sweep starts (a clear error, nothing stored)."""
        key = (scenario.id, n_vehicles)
        if self.net is None or getattr(self, "_key", None) != key:
            self.net = self._load(scenario.id, n_vehicles)
            self._key = key

    # ---------------------------------------------------------------- interface
    def messages(self, ctx: EpisodeContext) -> tuple[Message, ...]:
        """Every follower's vehicle block (5 floats) to both neighbours, and the learned message
        of FPrint, DIAL or CommNet (the network's ``msg_width`` floats) on its own channel."""
        self.preflight(ctx.scenario, ctx.n_vehicles)
        blocks = Message(f"{self.algo}-blocks", 5, "neighbours")
        if not self.net.msg_width:
            return (blocks,)
        return blocks, Message(f"{self.algo}-messages", self.net.msg_width, "neighbours")

    def reset(self, ctx: EpisodeContext) -> None:
        self.preflight(ctx.scenario, ctx.n_vehicles)
        self.params = ctx.params
        n = ctx.n_vehicles
        # at least MIN_LANES lanes: a matrix product of fewer rows takes other kernels whose
        # rounding differs from the rows of a batch; with >= MIN_LANES rows each row's numbers
        # do not depend on the batch, so an episode acts the same alone or batched (tested)
        self._lanes = max(ctx.batch_size, MIN_LANES)
        self.state = self.net.initial_state(self._lanes)
        self.seeds = ctx.seeds
        self.t = 0
        self._u_block: np.ndarray | None = None
        self._u_start = 0
        self.block_channel = ctx.channel(f"{self.algo}-blocks")
        self.msg_channel = ctx.channel(f"{self.algo}-messages") if self.net.msg_width else None
        # link order of "neighbours": (i-1 -> i) for i = 2..N, then (i+1 -> i) for i = 1..N-1
        self._n_front = n - 1

    def _uniforms(self, n: int) -> np.ndarray:
        """This step's action uniforms ``(B, N)``, drawn :data:`UNIFORM_BLOCK_STEPS` steps at a
        time (the same numbers as one draw per step, in one vectorised pass)."""
        k = self.t - self._u_start
        if self._u_block is None or k >= len(self._u_block):
            self._u_block = episode_uniforms(self.seeds, ACTION_STREAM, self.t, n,
                                             steps=UNIFORM_BLOCK_STEPS)
            self._u_start, k = self.t, 0
        return self._u_block[k]

    def _split(self, held: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
        """Received per-link messages ``(B, L, W)`` -> front and rear ``(B, N, W)`` (0 if none)."""
        b, _, w = held.shape
        front = np.zeros((b, n, w))
        rear = np.zeros((b, n, w))
        front[:, 1:] = held[:, : self._n_front]
        rear[:, :-1] = held[:, self._n_front :]
        return front, rear

    def act(self, state: PlatoonState, observation: np.ndarray | None) -> np.ndarray:
        import torch

        from marl.acting import policy_actions

        if observation is None:
            raise ConfigError(f"{self.algo} needs the agent observations (needs_observation)")
        b, n, _ = observation.shape

        def lanes(x: np.ndarray) -> np.ndarray:  # (b, ...) -> (lanes, ...), repeating row 0
            return x if b == self._lanes else np.concatenate([x, np.repeat(x[:1], self._lanes - b, 0)])

        own = observation[:, :, :5]
        payload = np.zeros((b, n + 1, 5))
        payload[:, 1:] = own
        front_blk, rear_blk = self._split(self.block_channel.transmit(payload), n)
        obs = lanes(np.concatenate([own, front_blk, rear_blk], axis=-1).astype(np.float32))
        messages: tuple[torch.Tensor | None, torch.Tensor | None] = (None, None)
        if self.msg_channel is not None:
            msg = self.net.message(self.state)[:, :b]  # (N, B, W)
            out = np.zeros((b, n + 1, self.net.msg_width))
            out[:, 1:] = msg.detach().numpy().transpose(1, 0, 2)
            f, r = self._split(self.msg_channel.transmit(out), n)

            def t(x: np.ndarray) -> torch.Tensor:
                return torch.from_numpy(lanes(x).transpose(1, 0, 2).astype(np.float32)).contiguous()

            messages = (t(f), t(r))
        uniforms = None
        if self.mode == "sampled":
            uniforms = lanes(self._uniforms(n))
        self.t += 1
        actions, self.state = policy_actions(self.net, obs, self.state, messages, uniforms)
        return action_to_command_mps2(
            actions[:b], state.gap_m, state.speed_mps, state.pred_speed_mps, self.params
        )

"""The population layer: K runs of one algorithm trained at once, each exactly as alone.

:class:`Trainer` stacks the K runs' networks as one network of ``K N`` agents
(:func:`stack_nets`; every layer is per agent, :mod:`marl.layers`), so each step acts for all
runs in one forward and each update (:class:`marl.a2c.Learner`) is one backward. It collects the
rollout: every live run steps its own env, ends its own segments and batches, and starts its
next batch at once (:meth:`Trainer.train`). K = 1 is one run. Training with validation and
checkpoint selection on top of it: :mod:`marl.selection`; ``docs/populations.md``.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from envs.dynamics import OBS_DIM
from envs.errors import ConfigError, TrainingDivergedError
from envs.params import RewardWeights
from envs.platoon import PlatoonEnv, StepResult
from envs.scenarios import Scenario, make_scenario
from marl.a2c import Learner, Run, Segment, training_device
from marl.config import A2CConfig, Algorithm
from marl.networks import AgentNet, State, exchange, neighbour_action_onehot

#: Structural fields every run of a population shares (they shape the stacked tensors and the
#: segment loop); the others may differ from run to run.
POPULATION_SHARED_FIELDS: tuple[str, ...] = ("hidden", "n_step", "episodes_parallel")


def stack_nets(algo: Algorithm, config: A2CConfig, nets: Sequence[AgentNet]) -> AgentNet:
    """One network of ``K N`` agents holding the K runs' networks' weights (and buffers) in
    order; its ``platoon_size`` is N."""
    n = nets[0].n_agents
    big = algo.build_net(config, n * len(nets), True, torch.Generator().manual_seed(0))
    parts = [dict(net.named_parameters()) | dict(net.named_buffers()) for net in nets]
    with torch.no_grad():
        for name, t in list(big.named_parameters()) + list(big.named_buffers()):
            t.copy_(torch.cat([part[name] for part in parts]))
    big.platoon_size = n
    return big


@dataclass
class _Batch:
    """A run's batch in progress: the batched env its B episodes run in (rows ``rows``, shared
    with the runs whose batch started at the same step), which of them still run, their
    training reward and length so far, its open segment (started at step ``seg_start`` of the
    loop) and whether it is over."""

    env: PlatoonEnv
    rows: slice
    active: np.ndarray
    ep_reward: np.ndarray
    ep_len: np.ndarray
    seg_start: int = 0
    seg: Segment = field(default_factory=Segment)
    steps: int = 0
    t_episode: int = 0
    done: bool = False


def _merge_rows(base: dict[str, Any], new: dict[str, Any], runs: Sequence[Run]) -> dict[str, Any]:
    """``base`` (an act's output, nested dicts of ``(A, ...)`` tensors) with the rows of
    ``runs`` taken from ``new``."""

    def merge(x: Any, y: Any) -> Any:
        if x is None:
            return None
        if isinstance(x, dict):
            return {k: merge(x[k], y[k]) for k in x}
        out = x.clone()
        for r in runs:
            out[r.rows] = y[r.rows]
        return out

    return {k: merge(base[k], new[k]) for k in base}


class Trainer(Learner):
    """On-policy A2C of K runs (a population; K = 1: one run) over batched envs.

    The K runs' agents are stacked as one network of ``K N`` agents (every layer is per agent,
    :mod:`marl.layers`), so each step acts for all runs in one forward and each update is one
    backward; everything that crosses agents (messages, the critic's neighbour actions,
    consensus, reward sharing) stays inside a run's platoon. Runs run free: each step acts
    for all of them, a run whose batch ended starts its next at once, and an update computes on
    the rows of the runs whose segment ended (:meth:`train`). Each run draws
    from its own generator in the order a run alone does, keeps its own environment, statistics
    and optimiser state, and so trains exactly as alone (tested to the last bit).

    Parameters
    ----------
    algo : Algorithm
    config : A2CConfig or sequence of them
        One config for every run, or one per run (equal in :data:`POPULATION_SHARED_FIELDS`).
    scenario_id : str
        The scenario's id (it names the checkpoints).
    n_vehicles : int
    seed : int or sequence of int
        The runs' seeds (one int: one run).
    device : str or torch.device
        Where the network, its gradients and optimiser state live (:func:`training_device`);
        the environments, the random streams and the checkpoints stay on the CPU, so the
        same seed draws the same actions' uniforms on every device.
    """

    def __init__(
        self,
        algo: Algorithm,
        config: A2CConfig | Sequence[A2CConfig],
        scenario_id: str,
        n_vehicles: int,
        seed: int | Sequence[int],
        device: str | torch.device = "cpu",
        scenario: Scenario | None = None,
    ) -> None:
        torch.set_num_threads(1)
        self.device = training_device(device)
        seeds = [int(seed)] if isinstance(seed, int | np.integer) else [int(s) for s in seed]
        configs = (
            [config] * len(seeds) if isinstance(config, A2CConfig) else list(config)
        )
        if not seeds or len(configs) != len(seeds):
            raise ConfigError(
                f"a population needs one config per seed (got {len(configs)} configs for "
                f"{len(seeds)} seeds)")
        self.algo = algo
        self.scenario_id = scenario_id
        # built once (or by the caller), for the config and every env of every run
        self.scenario = make_scenario(scenario_id) if scenario is None else scenario
        self.n_vehicles = n = n_vehicles
        resolved = [c.resolved(self.scenario) for c in configs]
        for f in POPULATION_SHARED_FIELDS:
            values = {getattr(c, f) for c in resolved}
            if len(values) > 1:
                raise ConfigError(
                    f"the runs of one population must share {f} (got {sorted(values)}); "
                    "train them in separate populations")
        self.shape = resolved[0]  # the shared structural fields
        self.runs: list[Run] = []
        nets = []
        for k, (s, cfg) in enumerate(zip(seeds, resolved, strict=True)):
            generator = torch.Generator().manual_seed(s)
            env = self._make_env(cfg.reward_weights())
            assert cfg.power_baseline_kw is not None  # resolved above
            run = Run(k, s, cfg, generator, env, slice(k * n, (k + 1) * n),
                      -cfg.reward_w_power * cfg.power_baseline_kw)
            with torch.device("cpu"):
                nets.append(algo.build_net(cfg, n, True, generator))
            self.runs.append(run)
        # built on the CPU from the CPU generators (the same initial weights on every device)
        with torch.device("cpu"):
            net = nets[0] if len(nets) == 1 else stack_nets(algo, resolved[0], nets)
        self.net = net.to(self.device)
        #: (parameter, is_critic): actor parameters, then the critic's
        self.params = [(p, False) for p in self.net.actor_parameters()] + [
            (p, True) for p in self.net.critic_parameters()]
        self._square_avg = [torch.zeros_like(p) for p, _ in self.params]
        self._views: dict[int, AgentNet] = {}
        for run in self.runs:
            algo.setup(run)

    # -- acting
    @torch.no_grad()
    def _act(self, obs: torch.Tensor, state: State, sampling: Sequence[Run]) -> dict[str, Any]:
        """No-grad acting step of the whole stack: observations ``(K N, B, 15)``, messages
        received, logits, actions, next state. Only the runs in ``sampling`` draw their actions
        (the others' rows are computed and ignored)."""
        net = self.net
        front, rear = exchange(net, state)
        logits, out, new = net.act_step(obs, state, front, rear,
                                        critic=not net.separate_critic)
        shape = (self.n_vehicles,) + tuple(logits.shape[1:])
        drawing = {r.index for r in sampling}
        parts = [r.uniforms(shape) if r.index in drawing else torch.full(shape, 0.5, device="cpu")
                 for r in self.runs]
        u = (parts[0] if len(parts) == 1 else torch.cat(parts)).to(self.device)
        actions = (logits - torch.log(-torch.log(u))).argmax(-1)
        return {"obs": obs, "front": front, "rear": rear, "out": out, "logits": logits,
                "actions": actions, "state": new}

    def _observation(self, obs_np: np.ndarray) -> torch.Tensor:
        """Env observations ``(B, N, 15)`` -> agent-major ``(N, B, 15)``."""
        return torch.from_numpy(obs_np).transpose(0, 1).contiguous().to(self.device)

    def run_batch(self, runs: Sequence[Run] | None = None) -> list[tuple[int, float]]:
        """Run one batch of B episodes of every run in ``runs`` (default all), with an update of
        each run every n steps.

        Returns per run the environment steps taken and the mean training reward (the
        learner's own, shaped when the config says so; mean over steps of the sum over agents,
        as the paper reports). Raises :class:`TrainingDivergedError` if a run diverged.
        """
        taking = list(self.runs if runs is None else runs)
        out: dict[int, tuple[int, float]] = {}

        def once(run: Run, steps: int, reward: float) -> bool:
            out[run.index] = (steps, reward)
            return False

        self.train(taking, once)
        failed = [r.failed for r in taking if r.failed is not None]
        if failed:
            raise TrainingDivergedError("; ".join(failed))
        return [out[r.index] for r in taking]

    def train(self, runs: Sequence[Run], on_batch: Callable[[Run, int, float], bool]) -> None:
        """Train ``runs`` batch after batch until ``on_batch`` says stop for each.

        The runs run free: every step acts for the whole stack at once, and each run steps its
        own env, ends its own segments (an update of exactly its rows) and batches, and starts
        its next batch at once. ``on_batch(run, steps, mean_training_reward)`` is called when a
        run's batch ended (after ``run.steps`` counts it) and returns whether the run goes on.
        A run that diverged stops there (``run.failed`` says why).
        """
        b = self.shape.episodes_parallel
        obs = [torch.zeros(self.n_vehicles, b, OBS_DIM, device=self.device)
               for _ in self.runs]  # idle runs: ignored
        state = self.net.initial_state(b)
        batch = self._start_batches(list(runs), obs, 0)
        live = list(runs)
        cur = self._act(self._stack(obs), state, live)
        #: per step since ``base``: the state acted from and what the act gave
        history: list[tuple[State, dict[str, Any]]] = []
        base = tick = 0
        while live:
            history.append((state, cur))
            next_state = cur["state"]
            # 1. every live run steps its env: some segments (``ending``) and batches (``over``)
            # end at this step
            ending, over = self._step_envs(live, batch, cur["actions"], obs)
            # 2. act on the next observations, with the weights before any update
            going = [r for r in live if r.index not in over]
            nxt = self._act(self._stack(obs), next_state, going) if going else None
            self._bootstrap_shared_critic(ending, over, batch, nxt)
            # 3. one update per segment length of the runs whose segment ended
            critic_after = self._update_ending(ending, batch, history, nxt)
            # 4. their next segments start from the same state, acting with the new weights
            reacting = self._next_segments(ending, over, batch, tick + 1)
            next_state, nxt = self._react(reacting, critic_after, next_state, nxt)
            # 5. runs whose batch ended report it; those that go on start their next batch
            restarting = self._end_batches(live, over, batch, on_batch)
            live = [r for r in live if r.index not in over] + restarting
            if restarting:
                next_state, nxt = self._restart(restarting, batch, obs, next_state, nxt, tick + 1)
            if not live:
                break
            assert nxt is not None
            state, cur = next_state, nxt
            tick += 1
            oldest = min(batch[r.index].seg_start for r in live)
            del history[: oldest - base]  # no open segment needs those steps
            base = oldest

    def _step_envs(
        self, live: list[Run], batch: dict[int, _Batch], actions: torch.Tensor,
        obs: list[torch.Tensor],
    ) -> tuple[list[Run], set[int]]:
        """Step every live run's env with its rows of ``actions`` and store its next
        observation in ``obs``; returns the runs whose segment ends at this step and the indices
        of those whose batch ends (a finished batch's segment bootstraps from 0)."""
        ending: list[Run] = []
        over: set[int] = set()
        sharing: dict[int, list[Run]] = {}  # env -> its live runs
        actions = actions.cpu()
        for r in live:
            sharing.setdefault(id(batch[r.index].env), []).append(r)
        for group in sharing.values():
            env = batch[group[0].index].env
            # rows of runs that left this env (their batch ended) step on with action 0, ignored
            acts = np.zeros((env.batch_size, self.n_vehicles), dtype=np.int64)
            for r in group:
                acts[batch[r.index].rows] = actions[r.rows].T.numpy()
            res = env.step_actions(acts)
            for r in group:
                bt = self._record(r, batch[r.index], res)
                if bt.done:
                    over.add(r.index)
                    bt.seg.bootstrap = torch.zeros(self.shape.episodes_parallel, self.n_vehicles,
                                                   device=self.device)
                    ending.append(r)
                else:
                    assert res.observation is not None
                    obs[r.index] = self._observation(res.observation[bt.rows])
                    if len(bt.seg.rews) == self.shape.n_step:
                        ending.append(r)
        return ending, over

    @torch.no_grad()
    def _bootstrap_shared_critic(
        self, ending: list[Run], over: set[int], batch: dict[int, _Batch],
        nxt: dict[str, Any] | None,
    ) -> None:
        """A critic that shares the actor's trunk bootstraps a segment that ended mid-batch from
        the act on the next observation (a separate critic's bootstrap comes from its recompute,
        in the update)."""
        net = self.net
        boot = [] if net.separate_critic else [r for r in ending if r.index not in over]
        if not boot:
            return
        assert nxt is not None
        values = net.value(nxt["out"], neighbour_action_onehot(nxt["actions"], net.platoon_size))
        for r in boot:
            batch[r.index].seg.bootstrap = values[r.rows].T

    def _update_ending(
        self, ending: list[Run], batch: dict[int, _Batch],
        record: list[tuple[State, dict[str, Any]]], nxt: dict[str, Any] | None,
    ) -> dict[int, State]:
        """Update the runs whose segment ended, one update per segment length (``record``: the
        steps kept, a segment of T steps being the last T); returns a separate critic's state
        after the segment per run."""
        by_length: dict[int, list[Run]] = {}
        for r in ending:
            by_length.setdefault(len(batch[r.index].seg.rews), []).append(r)
        critic_after: dict[int, State] = {}
        for t_len, group in sorted(by_length.items()):
            seg = record[-t_len:]
            critic_after |= self._update(group, seg[0][0], [h[1] for h in seg],
                                         [batch[r.index].seg for r in group], nxt)
        return critic_after

    def _next_segments(
        self, ending: list[Run], over: set[int], batch: dict[int, _Batch], tick: int
    ) -> list[Run]:
        """Open the next segment (from step ``tick``) of each run whose segment ended and whose
        batch goes on; a run that failed, or whose running episodes fell below
        ``min_active_fraction``, ends its batch instead (added to ``over``)."""
        reacting = []
        for r in ending:
            bt = batch[r.index]
            # most episodes ended (published collision rule): truncate the rest (their last
            # segment was bootstrapped) instead of stepping finished episodes
            if (r.failed is not None or r.index in over
                    or bt.active.sum() < r.config.min_active_fraction * self.shape.episodes_parallel):
                over.add(r.index)
                continue
            bt.seg, bt.seg_start = Segment(), tick
            reacting.append(r)
        return reacting

    def _react(
        self, reacting: list[Run], critic_after: dict[int, State], next_state: State,
        nxt: dict[str, Any] | None,
    ) -> tuple[State, dict[str, Any] | None]:
        """Act again for the runs that start a new segment, on the same observation and state,
        with their updated weights (the other runs keep what they drew); a separate critic's
        state at the segment start is its recompute's end."""
        if not reacting:
            return next_state, nxt
        if critic_after:
            next_state = {k: v.clone() for k, v in next_state.items()}
            for r in reacting:
                for k, v in critic_after[r.index].items():
                    next_state[k][r.rows] = v
        assert nxt is not None
        return next_state, _merge_rows(nxt, self._act(nxt["obs"], next_state, reacting), reacting)

    def _end_batches(
        self, live: list[Run], over: set[int], batch: dict[int, _Batch],
        on_batch: Callable[[Run, int, float], bool],
    ) -> list[Run]:
        """Count and report each ended batch (``on_batch``); returns the runs that go on."""
        restarting = []
        for r in live:
            if r.index not in over:
                continue
            bt = batch.pop(r.index)
            if r.failed is not None:
                continue
            r.steps += bt.steps
            r.episodes += self.shape.episodes_parallel
            if on_batch(r, bt.steps, float((bt.ep_reward / np.maximum(bt.ep_len, 1)).mean())):
                restarting.append(r)
        return restarting

    def _restart(
        self, restarting: list[Run], batch: dict[int, _Batch], obs: list[torch.Tensor],
        next_state: State, nxt: dict[str, Any] | None, tick: int,
    ) -> tuple[State, dict[str, Any]]:
        """Start the next batch of each run in ``restarting`` at step ``tick``: new episodes,
        the initial recurrent state on its rows, and its first act."""
        initial = self.net.initial_state(self.shape.episodes_parallel)
        next_state = {k: v.clone() for k, v in next_state.items()}
        batch |= self._start_batches(restarting, obs, tick)
        for r in restarting:
            for k, v in next_state.items():
                v[r.rows] = initial[k][r.rows]
        new = self._act(self._stack(obs), next_state, restarting)
        return next_state, new if nxt is None else _merge_rows(nxt, new, restarting)

    def _make_env(self, weights: RewardWeights) -> PlatoonEnv:
        """A batched training env of the scenario (published collision rule, ``weights``)."""
        return PlatoonEnv(self.scenario, self.n_vehicles, training=True,
                          collision_mode="published", weights=weights)

    def _start_batches(self, runs: list[Run], obs: list[torch.Tensor], tick: int
                       ) -> dict[int, _Batch]:
        """Start the next batch of each run in ``runs`` at step ``tick``: the runs with the same
        reward weights share one batched env of their K B episodes (each episode depends on its
        own seed only, so a run's rows equal its env alone; one step of a shared env costs about
        what one run's costs)."""
        b, n = self.shape.episodes_parallel, self.n_vehicles
        by_weights: dict[RewardWeights, list[Run]] = {}
        for r in runs:
            by_weights.setdefault(r.env.weights, []).append(r)
        out = {}
        for weights, group in by_weights.items():
            env = self._make_env(weights)
            obs_np = env.reset(np.concatenate([r.training_seeds(b) for r in group]))
            assert obs_np is not None
            for j, r in enumerate(group):
                rows = slice(j * b, (j + 1) * b)
                obs[r.index] = self._observation(obs_np[rows])
                r.return_acc = torch.zeros(b, n, device=self.device)
                out[r.index] = _Batch(env, rows, np.ones(b, dtype=bool), np.zeros(b),
                                      np.zeros(b), seg_start=tick)
        return out

    def _record(self, r: Run, bt: _Batch, res: StepResult) -> _Batch:
        """Record the run's rows of its env's step ``res`` in its batch and open segment."""
        sg, act, rows = bt.seg, bt.active, bt.rows
        done, collided, reward = res.done[rows], res.collided[rows], res.reward[rows]
        bt.t_episode += 1
        sg.masks.append(act.copy())
        sg.terms.append(done & act)
        if r.baseline_reward:
            running = act & ~collided
            sg.rews.append(reward + r.baseline_reward * running[:, None])
        else:
            sg.rews.append(reward)
        crashed = done & collided & act
        sg.absorbed.append(
            r.absorbing_value(r.env.n_steps - bt.t_episode) * crashed
            if crashed.any() else np.zeros(len(act))
        )
        bt.steps += int(act.sum())
        bt.ep_reward += np.where(act, sg.rews[-1].sum(1), 0.0)
        bt.ep_len += act
        bt.active = ~done
        bt.done = bool(done.all())
        return bt

    def _stack(self, parts: list[torch.Tensor]) -> torch.Tensor:
        return parts[0] if len(parts) == 1 else torch.cat(parts)


    # -- one run's view
    def run_net(self, run: Run) -> AgentNet:
        """The run's acting network as its checkpoint stores it: N agents, no critic, weights
        rounded to the checkpoint's precision (validation scores what is saved, and a saved
        snapshot scores in the harness exactly what validation measured)."""
        from marl.checkpoint import WEIGHT_DTYPE

        view = self._views.get(run.index)
        if view is None:
            with torch.device("cpu"):  # validation and checkpoints on the CPU
                view = self.algo.build_net(run.config, self.n_vehicles, False,
                                           torch.Generator().manual_seed(0))
            view.requires_grad_(False)
            self._views[run.index] = view
        whole = dict(self.net.named_parameters())
        with torch.no_grad():
            for name, p in view.named_parameters():
                p.copy_(whole[name][run.rows].to(WEIGHT_DTYPE))
        return view


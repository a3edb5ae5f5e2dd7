"""The population layer: K runs of one algorithm trained at once, each exactly as alone.

:class:`PopulationTrainer` wraps the single-run learner (:class:`marl.a2c.Trainer`): it stacks
the K runs' networks as one network of ``K N`` agents (:func:`stack_nets`; every layer is per
agent, :mod:`marl.layers`), so each step acts for all runs in one forward and each update is one
backward of the runs whose segments ended. Every live run steps its own env, ends its own
segments and batches, and starts its next batch at once (:meth:`PopulationTrainer.train`).
Training with validation and checkpoint selection on top of it: :mod:`marl.selection`;
``docs/populations.md``.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import torch

from envs.dynamics import OBS_DIM
from envs.params import RewardWeights
from envs.scenarios import Scenario, make_scenario
from infra.errors import ConfigError, TrainingDivergedError
from marl.a2c import Batch, Run, Segment, Trainer, segment_loss
from marl.config import A2CConfig, Algorithm
from marl.layers import per_agent_clip_, rmsprop_
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


class PopulationTrainer(Trainer):
    """On-policy A2C of K runs at once over batched envs, each exactly as
    :class:`marl.a2c.Trainer` trains it alone.

    The K runs' agents are stacked as one network of ``K N`` agents (every layer is per agent,
    :mod:`marl.layers`), so each step acts for all runs in one forward and each update is one
    backward; everything that crosses agents (messages, the critic's neighbour actions,
    consensus, reward sharing) stays inside a run's platoon. Runs run free: each step acts
    for all of them, a run whose batch ended starts its next at once, and an update computes on
    the rows of the runs whose segment ended (:meth:`train`). Each run draws from its own
    generator in the order a run alone does, keeps its own environment, statistics and optimiser
    state, and so trains exactly as alone (tested to the last bit against the single-run
    learner).

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
        the environments, the random streams and the checkpoints stay on the CPU.
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
        seeds = [int(seed)] if isinstance(seed, int | np.integer) else [int(s) for s in seed]
        configs = (
            [config] * len(seeds) if isinstance(config, A2CConfig) else list(config)
        )
        if not seeds or len(configs) != len(seeds):
            raise ConfigError(
                f"a population needs one config per seed (got {len(configs)} configs for "
                f"{len(seeds)} seeds)")
        # built once (or by the caller), for the config and every env of every run
        scenario = make_scenario(scenario_id) if scenario is None else scenario
        resolved = [c.resolved(scenario) for c in configs]
        for f in POPULATION_SHARED_FIELDS:
            values = {getattr(c, f) for c in resolved}
            if len(values) > 1:
                raise ConfigError(
                    f"the runs of one population must share {f} (got {sorted(values)}); "
                    "train them in separate populations")
        self._start(algo, scenario_id, scenario, n_vehicles, seeds, resolved, device)

    def _join(self, nets: list[AgentNet]) -> AgentNet:
        """The K runs' networks stacked as one (built on the CPU from the CPU generators)."""
        if len(nets) == 1:
            return nets[0]
        with torch.device("cpu"):
            return stack_nets(self.algo, self.shape, nets)

    # -- acting
    @torch.no_grad()
    def _act(self, obs: torch.Tensor, state: State, sampling: Sequence[Run] | None = None
             ) -> dict[str, Any]:
        """No-grad acting step of the whole stack: observations ``(K N, B, 15)``, messages
        received, logits, actions, next state. Only the runs in ``sampling`` draw their actions
        (the others' rows are computed and ignored; default all)."""
        net = self.net
        front, rear = exchange(net, state)
        logits, out, new = net.act_step(obs, state, front, rear,
                                        critic=not net.separate_critic)
        shape = (self.n_vehicles,) + tuple(logits.shape[1:])
        drawing = {r.index for r in (self.runs if sampling is None else sampling)}
        parts = [r.uniforms(shape) if r.index in drawing else torch.full(shape, 0.5, device="cpu")
                 for r in self.runs]
        u = (parts[0] if len(parts) == 1 else torch.cat(parts)).to(self.device)
        actions = (logits - torch.log(-torch.log(u))).argmax(-1)
        return {"obs": obs, "front": front, "rear": rear, "out": out, "logits": logits,
                "actions": actions, "state": new}

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

        self.train(once, taking)
        failed = [r.failed for r in taking if r.failed is not None]
        if failed:
            raise TrainingDivergedError("; ".join(failed))
        return [out[r.index] for r in taking]

    def train(self, on_batch: Callable[[Run, int, float], bool],
              runs: Sequence[Run] | None = None) -> None:
        """Train ``runs`` (default all) batch after batch until ``on_batch`` says stop for each.

        The runs run free: every step acts for the whole stack at once, and each run steps its
        own env, ends its own segments (an update of exactly its rows) and batches, and starts
        its next batch at once. ``on_batch(run, steps, mean_training_reward)`` is called when a
        run's batch ended (after ``run.steps`` counts it) and returns whether the run goes on.
        A run that diverged stops there (``run.failed`` says why).
        """
        live = list(self.runs if runs is None else runs)
        b = self.shape.episodes_parallel
        obs = [torch.zeros(self.n_vehicles, b, OBS_DIM, device=self.device)
               for _ in self.runs]  # idle runs: ignored
        state = self.net.initial_state(b)
        batch = self._start_batches(live, obs, 0)
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
        self, live: list[Run], batch: dict[int, Batch], actions: torch.Tensor,
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
        self, ending: list[Run], over: set[int], batch: dict[int, Batch],
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
        self, ending: list[Run], batch: dict[int, Batch],
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
            critic_after |= self._update_group(group, seg[0][0], [h[1] for h in seg],
                                               [batch[r.index].seg for r in group], nxt)
        return critic_after

    def _next_segments(
        self, ending: list[Run], over: set[int], batch: dict[int, Batch], tick: int
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
        self, live: list[Run], over: set[int], batch: dict[int, Batch],
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
        self, restarting: list[Run], batch: dict[int, Batch], obs: list[torch.Tensor],
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

    def _start_batches(self, runs: list[Run], obs: list[torch.Tensor], tick: int
                       ) -> dict[int, Batch]:
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
                out[r.index] = Batch(env, rows, np.ones(b, dtype=bool), np.zeros(b),
                                      np.zeros(b), seg_start=tick)
        return out

    def _stack(self, parts: list[torch.Tensor]) -> torch.Tensor:
        return parts[0] if len(parts) == 1 else torch.cat(parts)

    # -- update of a group of runs (one, or several whose segments ended together)
    def _update_group(
        self, group: list[Run], seg_state: State, record: list[dict[str, Any]],
        segs: list[Segment], nxt: dict[str, Any] | None,
    ) -> dict[int, State]:
        """:meth:`marl.a2c.Trainer._update` of every run in ``group`` (their segments have the
        same length) on their rows: one recompute, each run's loss, one backward; returns a
        separate critic's state after the segment per continuing run."""
        logits, values, actions, rows, after = self._recompute_group(group, seg_state, record)
        critic_after = self._critic_bootstrap_group(group, segs, rows, after, nxt)
        losses = [segment_loss(r, sg, logits, values, actions, rw)
                  for r, sg, rw in zip(group, segs, rows, strict=True)]
        loss = losses[0]
        for other in losses[1:]:  # each run's gradient is its own loss's (the sum's is 1 each)
            loss = loss + other
        self._optimise(loss, group)
        return critic_after

    def _recompute_group(
        self, group: list[Run], seg_state: State, record: list[dict[str, Any]]
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, list[slice], State]:
        """Re-run the group's segment with gradient on the group's rows only: logits
        ``(A, T, B, 4)``, values and actions ``(A, T, B)`` of its ``A`` agents, each run's rows
        among them, and the recurrent state after the segment (those rows)."""
        if len(group) == len(self.runs):
            logits, values, actions, after = self._recompute(seg_state, record)
            return logits, values, actions, [r.rows for r in group], after
        net = self.net
        idx = torch.cat([torch.arange(r.rows.start, r.rows.stop, device=self.device)
                         for r in group])

        def pick(t: torch.Tensor) -> torch.Tensor:
            return t.index_select(0, idx)

        obs, actions, msgs = self._segment_inputs(record)
        if msgs is not None:
            msgs = (pick(msgs[0]), pick(msgs[1]))
        tensors = {name: pick(t) for name, t in [*net.named_parameters(), *net.named_buffers()]}
        logits, values, after = torch.func.functional_call(net, tensors, (
            {k: pick(v) for k, v in seg_state.items()}, pick(obs), pick(actions), msgs))
        n = self.n_vehicles
        rows = [slice(j * n, (j + 1) * n) for j in range(len(group))]
        return logits, values, pick(actions), rows, after

    @torch.no_grad()
    def _critic_bootstrap_group(
        self, group: list[Run], segs: list[Segment], rows: list[slice], after: State,
        nxt: dict[str, Any] | None,
    ) -> dict[int, State]:
        """:meth:`marl.a2c.Trainer._critic_bootstrap` of each continuing run of the group, in
        one critic step of the whole stack."""
        net = self.net
        if not net.separate_critic:
            return {}
        going = [(r, sg, rw) for r, sg, rw in zip(group, segs, rows, strict=True)
                 if sg.bootstrap is None]
        if not going:
            return {}
        assert nxt is not None
        b = self.shape.episodes_parallel
        start = {k: torch.zeros(net.n_agents, b, net.hidden, device=self.device)
                 for k in ("ch", "cc")}
        for r, _, rw in going:
            for k in start:
                start[k][r.rows] = after[k][rw]
        out, _ = net.critic_features(nxt["obs"], start)
        values = net.value(out, neighbour_action_onehot(nxt["actions"], net.platoon_size))
        for r, sg, _ in going:
            sg.bootstrap = values[r.rows].T
        return {r.index: {k: after[k][rw].detach().clone() for k in ("ch", "cc")}
                for r, _, rw in going}

    def _clip(self, runs: list[Run]) -> None:
        """Clip each agent's gradient to its run's global norm (the other rows have none)."""
        clips = {r.config.grad_clip for r in runs}
        params = [p for p, _ in self.params]
        if len(clips) == 1:
            per_agent_clip_(params, clips.pop())
        else:  # a config population: each run clips at its own norm
            per_agent_clip_(params, torch.tensor(
                [r.config.grad_clip for r in self.runs], device=self.device
            ).repeat_interleave(self.n_vehicles))

    @torch.no_grad()
    def _rmsprop_step(self, runs: list[Run]) -> None:
        """RMSprop on the rows of ``runs``, each with its own rates, smoothing and epsilon (one
        step of the whole stack when every run updates with the same settings)."""
        settings = {(r.learning_rates(), r.config.rmsprop_alpha, r.config.rmsprop_eps)
                    for r in runs}
        if len(runs) == len(self.runs) and len(settings) == 1:
            (lrs, alpha, eps), = settings
            for (p, is_critic), sq in zip(self.params, self._square_avg, strict=True):
                assert p.grad is not None
                rmsprop_(p, p.grad, sq, lrs[is_critic], alpha, eps)
            return
        for (p, is_critic), sq in zip(self.params, self._square_avg, strict=True):
            assert p.grad is not None
            for r in runs:
                cfg = r.config
                rmsprop_(p[r.rows], p.grad[r.rows], sq[r.rows], r.learning_rates()[is_critic],
                         cfg.rmsprop_alpha, cfg.rmsprop_eps)

"""MAPPO training throughput of TorchRL and BenchMARL on the batched platoon environment.

Documentation for issue 31 (docs/notes/marl-library-choice.md: results, and the commands of the
separate venv with torchrl and benchmarl that this needs); not run by CI, not imported by tests.
``python docs/scripts/torchrl_throughput.py {torchrl,benchmarl,env} --threads 1``. Unit: steps
of one episode (all N followers) per second, B per ``PlatoonEnv.step``, as ``cacc-bench perf``
counts; collection, GAE and PPO updates after ``--warmup`` iterations, wall clock and CPU time.
"""

from __future__ import annotations

import argparse
import tempfile
import time

import numpy as np
import torch
from benchmarl.algorithms import IppoConfig, MappoConfig
from benchmarl.environments.common import TaskClass
from benchmarl.experiment import Experiment, ExperimentConfig
from benchmarl.experiment.callback import Callback
from benchmarl.models.mlp import MlpConfig
from tensordict import TensorDict
from tensordict.nn import NormalParamExtractor, TensorDictModule
from torch import nn
from torchrl.collectors import Collector
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase
from torchrl.modules import MultiAgentMLP, ProbabilisticActor, TanhNormal, ValueOperator
from torchrl.objectives import ClipPPOLoss, ValueEstimators

from envs.platoon import PlatoonEnv

AGENTS = "agents"


class PlatoonTorchEnv(EnvBase):
    """The batched ``PlatoonEnv`` (accel mode) as a TorchRL env of batch size ``[B]``.

    Group ``agents``: observation ``(B, N, obs_dim)``, action ``(B, N, 1)`` in the command
    bounds, reward ``(B, N, 1)``; done/terminated/truncated ``(B, 1)`` at the root (terminated:
    a collision; truncated: the time limit). All B episodes step together: a partial reset (an
    episode that ended early) leaves it frozen (reward 0) until all are done, then all restart.
    """

    def __init__(self, scenario: str = "catchup-v1", n_vehicles: int = 8, num_envs: int = 64,
                 seed: int = 0, reward_scale: float = 0.01) -> None:
        super().__init__(batch_size=torch.Size([num_envs]), device="cpu")
        self.env = PlatoonEnv(scenario, n_vehicles, training=True, action_mode="accel")
        self.n_vehicles, self.num_envs, self.reward_scale = n_vehicles, num_envs, reward_scale
        self._next_seed, self._obs = 1_000_000 * seed, torch.empty(0)
        b, n, p = num_envs, n_vehicles, self.env.params

        def group(**specs):
            return Composite({AGENTS: Composite(**specs, shape=(b, n))}, shape=(b,))

        self.observation_spec = group(observation=Unbounded((b, n, self.env.obs_dim)))
        self.action_spec = group(action=Bounded(p.accel_min_mps2, p.accel_max_mps2, (b, n, 1)))
        self.reward_spec = group(reward=Unbounded((b, n, 1)))
        flag = Categorical(2, (b, 1), dtype=torch.bool)
        self.done_spec = Composite(done=flag, terminated=flag.clone(), truncated=flag.clone(),
                                   shape=(b,))

    def _td(self, done: np.ndarray, collided: np.ndarray, **agents: torch.Tensor) -> TensorDict:
        d, c = torch.from_numpy(done)[:, None], torch.from_numpy(collided & done)[:, None]
        group = TensorDict(agents, batch_size=(self.num_envs, self.n_vehicles))
        return TensorDict({AGENTS: group, "done": d, "terminated": c, "truncated": d & ~c},
                          batch_size=self.batch_size)

    def _reset(self, tensordict: TensorDict | None = None, **kwargs) -> TensorDict:
        mask = None if tensordict is None else tensordict.get("_reset", None)
        if self._obs.numel() == 0 or mask is None or bool(mask.all()):
            seeds = np.arange(self._next_seed, self._next_seed + self.num_envs)
            self._next_seed += self.num_envs
            self._obs = torch.from_numpy(np.array(self.env.reset(seeds), dtype=np.float32))
        no = np.zeros(self.num_envs, dtype=bool)
        return self._td(no, no, observation=self._obs.clone())

    def _step(self, tensordict: TensorDict) -> TensorDict:
        command = tensordict.get((AGENTS, "action")).squeeze(-1).to(torch.float64).numpy()
        res = self.env.step(command)
        self._obs = torch.from_numpy(np.array(res.observation, dtype=np.float32))
        reward = torch.from_numpy((self.reward_scale * res.reward).astype(np.float32))[..., None]
        return self._td(res.done, res.collided, observation=self._obs.clone(), reward=reward)

    def _set_seed(self, seed: int | None) -> None:
        self._next_seed = 1_000_000 * (seed or 0)


class PlatoonTask(TaskClass):
    """BenchMARL task over :class:`PlatoonTorchEnv` (name: the scenario id; vectorised)."""

    def get_env_fun(self, num_envs, continuous_actions, seed, device):
        cfg = self.config
        return lambda: PlatoonTorchEnv(self.name, cfg["n_vehicles"], num_envs, seed or 0,
                                       cfg["reward_scale"])

    def supports_continuous_actions(self): return True
    def supports_discrete_actions(self): return False
    def max_steps(self, env): return env.env.n_steps
    def has_render(self, env): return False
    def group_map(self, env): return {AGENTS: [f"follower_{i}" for i in range(env.n_vehicles)]}
    def observation_spec(self, env): return env.full_observation_spec_unbatched.clone()
    def info_spec(self, env): return None
    def state_spec(self, env): return None
    def action_spec(self, env): return env.full_action_spec_unbatched
    def action_mask_spec(self, env): return None

    @staticmethod
    def env_name(): return "platoon"


class Plain(nn.Module):
    """The shared network as plain torch (``--plain``): one MLP over the last axis; centralised:
    over all agents' observations, its value given to every agent."""

    def __init__(self, n_in: int, n_out: int, n_agents: int, centralised: bool) -> None:
        super().__init__()
        self.n_agents, self.centralised = n_agents, centralised
        self.net = nn.Sequential(nn.Linear(n_in * (n_agents if centralised else 1), 64),
                                 nn.Tanh(), nn.Linear(64, 64), nn.Tanh(), nn.Linear(64, n_out))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if not self.centralised:
            return self.net(x)
        out = self.net(x.flatten(-2)).unsqueeze(-2)
        return out.expand(*out.shape[:-2], self.n_agents, out.shape[-1])


def mlp(n_in: int, n_out: int, n_agents: int, centralised: bool, plain: bool) -> nn.Module:
    """Two hidden layers of 64, tanh, one set of weights for all agents."""
    if plain:
        return Plain(n_in, n_out, n_agents, centralised)
    return MultiAgentMLP(n_agent_inputs=n_in, n_agent_outputs=n_out, n_agents=n_agents,
                         centralised=centralised, share_params=True, depth=2, num_cells=64,
                         activation_class=nn.Tanh)


class Stop(Exception):
    """Ends a training loop once the timing is long enough."""


class Clock(Callback):
    """Time stamps of the iterations, batch in hand (``marks``) and update done (``ends``); a
    BenchMARL callback, called by hand in the TorchRL loop. Raises :class:`Stop` when done."""

    def __init__(self, args: argparse.Namespace) -> None:
        super().__init__()
        self.args = args
        self.marks: list[float] = []
        self.cpu: list[float] = []
        self.ends: list[float] = []
        self.frames: list[int] = []
        self.rewards: list[float] = []

    def on_batch_collected(self, batch: TensorDict) -> None:
        self.marks.append(time.perf_counter())
        self.cpu.append(time.process_time())
        self.frames.append(batch.numel())
        self.rewards.append(float(batch.get(("next", AGENTS, "reward")).mean()))
        w = self.args.warmup
        if len(self.marks) > w and self.marks[-1] - self.marks[w] >= self.args.seconds:
            raise Stop

    def on_train_end(self, training_td: TensorDict | None = None, group: str = "") -> None:
        self.ends.append(time.perf_counter())

    def report(self, name: str) -> None:
        args, m = self.args, self.marks
        w = args.warmup
        seconds, cpu = m[-1] - m[w], self.cpu[-1] - self.cpu[w]
        collect = sum(m[i] - self.ends[i - 1] for i in range(w + 1, len(m)))
        steps = sum(self.frames[w + 1:])  # the batches collected between the marks
        kind = "plain" if args.plain and name == "torchrl" else "library"
        print(f"{name} {'ippo' if args.ippo else 'mappo'} {kind} threads={args.threads} "
              f"B={args.envs} T={args.rollout} iters={len(m) - 1 - w} wall_s={seconds:.1f} "
              f"env_steps={steps} env_steps_per_s={steps / seconds:.0f} "
              f"per_cpu_s={steps / cpu:.0f} collect_share={collect / seconds:.2f} "
              f"step_reward first={self.rewards[0]:.3f} last={self.rewards[-1]:.3f}", flush=True)


def run_torchrl(args: argparse.Namespace) -> None:
    """Raw TorchRL: Collector + GAE + ClipPPOLoss; MAPPO: a centralised shared critic."""
    env = PlatoonTorchEnv(args.scenario, args.vehicles, args.envs, 0, args.reward_scale)
    n, d, clock = args.vehicles, env.env.obs_dim, Clock(args)
    obs, act, loc, scale = ((AGENTS, k) for k in ("observation", "action", "loc", "scale"))
    actor = ProbabilisticActor(
        TensorDictModule(nn.Sequential(mlp(d, 2, n, False, args.plain), NormalParamExtractor()),
                         in_keys=[obs], out_keys=[loc, scale]),
        spec=env.full_action_spec_unbatched[act], in_keys=[loc, scale], out_keys=[act],
        distribution_class=TanhNormal, distribution_kwargs={"low": -2.5, "high": 2.5},
        return_log_prob=True)
    critic = ValueOperator(mlp(d, 1, n, not args.ippo, args.plain), in_keys=[obs],
                           out_keys=[(AGENTS, "state_value")])
    collector = Collector(env, actor, frames_per_batch=args.envs * args.rollout, total_frames=-1)
    loss = ClipPPOLoss(actor, critic, clip_epsilon=0.2, entropy_bonus=False,
                       normalize_advantage=False)
    loss.set_keys(reward=(AGENTS, "reward"), action=act, value=(AGENTS, "state_value"),
                  done=(AGENTS, "done"), terminated=(AGENTS, "terminated"),
                  sample_log_prob=(AGENTS, "action_log_prob"))
    loss.make_value_estimator(ValueEstimators.GAE, gamma=0.99, lmbda=0.95)
    optim = torch.optim.Adam(loss.parameters(), lr=3e-4)
    mb = max(1, args.minibatch // n)  # agent-samples -> environment steps per minibatch
    try:
        for data in collector:
            clock.on_batch_collected(data)
            for key in ("done", "terminated"):
                data.set(("next", AGENTS, key), data.get(("next", key)).unsqueeze(-1).expand(
                    data.get_item_shape(("next", AGENTS, "reward"))))
            with torch.no_grad():
                loss.value_estimator(data, params=loss.critic_network_params,
                                     target_params=loss.target_critic_network_params)
            flat = data.reshape(-1)
            for _ in range(args.epochs):
                for idx in torch.randperm(flat.numel()).split(mb):
                    out = loss(flat[idx])
                    (out["loss_objective"] + out["loss_critic"]).backward()
                    nn.utils.clip_grad_norm_(loss.parameters(), 0.5)
                    optim.step()
                    optim.zero_grad()
            collector.update_policy_weights_()
            clock.on_train_end()
    except Stop:
        pass
    collector.shutdown()
    clock.report("torchrl")


def run_benchmarl(args: argparse.Namespace) -> None:
    """BenchMARL's own experiment loop (its MappoConfig or IppoConfig) over PlatoonTask."""
    clock = Clock(args)
    config = ExperimentConfig.get_from_yaml()
    for key, value in dict(
            loggers=[], evaluation=False, render=False, create_json=False, checkpoint_interval=0,
            checkpoint_at_end=False, max_n_frames=None, max_n_iters=1_000_000, lr=3e-4,
            on_policy_collected_frames_per_batch=args.envs * args.rollout,
            on_policy_n_envs_per_worker=args.envs, on_policy_n_minibatch_iters=args.epochs,
            on_policy_minibatch_size=max(1, args.minibatch // args.vehicles),
            save_folder=tempfile.mkdtemp()).items():
        setattr(config, key, value)
    model = MlpConfig(num_cells=[64, 64], activation_class=nn.Tanh, layer_class=nn.Linear)
    task = PlatoonTask(args.scenario, {"n_vehicles": args.vehicles,
                                       "reward_scale": args.reward_scale})
    experiment = Experiment(task=task, algorithm_config=(IppoConfig if args.ippo else MappoConfig)
                            .get_from_yaml(), model_config=model, critic_model_config=model,
                            seed=0, config=config, callbacks=[clock])
    try:
        experiment.run()
    except Stop:
        pass
    clock.report("benchmarl")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("level", choices=["torchrl", "benchmarl", "env"])
    for name, default in [("threads", 1), ("seconds", 60.0), ("warmup", 2), ("envs", 64),
                          ("rollout", 128), ("epochs", 4), ("minibatch", 4096), ("vehicles", 8),
                          ("scenario", "catchup-v1"), ("reward-scale", 0.01)]:
        p.add_argument(f"--{name}", type=type(default), default=default)
    p.add_argument("--ippo", action="store_true", help="decentralised critic (IPPO)")
    p.add_argument("--plain", action="store_true", help="torchrl: plain torch MLPs")
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    if args.level == "env":  # the wrapped environment alone, random actions
        env, t0 = PlatoonTorchEnv(args.scenario, args.vehicles, args.envs), time.perf_counter()
        td = env.rollout(args.rollout * 4, break_when_any_done=False)
        rate = td.numel() / (time.perf_counter() - t0)
        return print(f"env threads={args.threads} env_steps_per_s={rate:.0f}", flush=True)
    (run_torchrl if args.level == "torchrl" else run_benchmarl)(args)


if __name__ == "__main__":
    main()

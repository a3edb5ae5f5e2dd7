"""What an algorithm is: the learners' shared config (:class:`A2CConfig`) and the
:class:`Algorithm` record each algorithm file fills, with the registry that finds them.

Every algorithm file (``ia2c.py``, ``fprint.py``, ``dial.py``, ``commnet.py``, ``wac.py``,
``dcea.py``, ``bdc.py``) defines its config (a frozen subclass of :class:`A2CConfig`), its
network (a subclass of :class:`marl.networks.AgentNet`) and what it does around the update as
plain functions, gathered in its ``ALGORITHM`` (an :class:`Algorithm`). This module imports
neither the learner nor torch's training code, so acting from a checkpoint
(:mod:`marl.acting`, :mod:`controllers.policy`) loads only configs and networks; the learner
that trains them is :mod:`marl.a2c`.
"""

from __future__ import annotations

import copy
import dataclasses
import importlib
import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, ClassVar, Protocol

import numpy as np

from envs.params import EVAL_MODES, RewardWeights
from envs.scenarios import Scenario, as_scenario, scenario_family
from infra.errors import ConfigError, UnknownNameError
from marl.learners import PAPER_ALGORITHMS

if TYPE_CHECKING:
    import torch

    from marl.networks import AgentNet

COLLISION_VALUES: tuple[str, ...] = ("absorbing", "published")


# ---------------------------------------------------------------------------- config
@dataclass(frozen=True)
class A2CConfig:
    """Hyper-parameters shared by every learner (paper values; published code's where silent).

    Attributes
    ----------
    n_step : int
        Steps per update segment (published 60).
    gamma : float
        Discount (paper 0.99).
    hidden : int
        Width of the FC encoder and the LSTM (paper 64).
    actor_lr, critic_lr : float
        RMSprop learning rates of actor and critic parameters (paper 5e-4 and 2.5e-4; a shared
        trunk learns at the actor rate).
    rmsprop_alpha, rmsprop_eps : float
        RMSprop smoothing and epsilon (published 0.99, 1e-5).
    entropy_coef, value_coef : float
        Loss weights (published 0.05 and 0.5).
    grad_clip : float
        Global grad-norm clip per agent (published 40).
    reward_scale : float
        Rewards are multiplied by this for learning (published 1/800 IA2C family, 1/5000
        DIAL/CommNet).
    reward_alpha : float or None
        Reward sharing: agent i learns from ``sum_j alpha^|i-j| r_j`` (0 local, 1 global). None
        (default): the published config's value for the scenario family and the algorithm's
        family (:attr:`PUBLISHED_REWARD_ALPHA`; the IA2C family uses 1 on catchup and 0 on
        slowdown, DIAL and CommNet 1 everywhere, the consensus family WAC, DCEA and BDC 0
        everywhere), resolved when training starts and recorded in
        the checkpoint.
    entropy_coef_final : float or None
        Entropy coefficient reached at the end of the run, linearly from ``entropy_coef``
        (None: constant, as published; default 0.005, a departure).
    return_norm : bool
        Divide the (scaled, shared) rewards by the running standard deviation of the discounted
        return before the update (off by default, as published).
    collision_value : {"absorbing", "published"}
        What an episode ended early by the published collision rule is worth afterwards:
        ``published`` 0 (terminal); ``absorbing`` (default, a departure) the collision penalty at
        every step to the scheduled end, folded into the last step's return.
    advantage_norm : bool
        Standardise each agent's advantages over the running entries of every segment before
        the policy loss (:func:`marl.a2c.normalise_advantages`; off by default, as published).
    episodes_parallel : int
        B episodes stepped together (sample budget counts all of them).
    lr_scale : float
        Multiplier on both learning rates (4.0 with B = 8; 1.0: the paper's per-update rates).
    eval_every_steps : int
        Environment steps between evaluations on the validation seeds, in both modes (learning
        curve and checkpoint selection: the kept snapshot is the evaluated one with the fewest
        collisions, then the best reward, in ``selection_mode``; a tie goes to the later one).
    selection_mode : {"sampled", "greedy"}
        Evaluation mode in which the kept snapshot is chosen on the validation seeds (the mode
        the policy controller is evaluated in; default ``sampled``, the policy as trained).
    reward_w_gap, reward_w_speed, reward_w_accel, reward_w_safety, reward_w_power : float
        Weights w1..w5 of the **training** reward (paper: -1, -1, -0.1, -5, -10; power in kW).
        The benchmark always scores with the paper's weights; other values are a documented
        shaping of the learning signal, recorded in the checkpoint.
    power_baseline_kw : float or None
        Constant power subtracted from every running agent's power for learning: the power term
        becomes ``w5 (P - P0)``. 0 (default): the paper's term. None: the cruise power
        ``P(v*, 0)`` at the scenario's target speed, resolved when training starts and recorded.
    min_active_fraction : float
        At an n-step boundary, when fewer than this fraction of the B episodes are still running,
        the rest are truncated (bootstrapped) and a new batch starts (0, default: never).

    Why each departure exists and what the options measured: ``docs/learner-options.md``.
    """

    n_step: int = 60
    gamma: float = 0.99
    hidden: int = 64
    actor_lr: float = 5e-4
    critic_lr: float = 2.5e-4
    rmsprop_alpha: float = 0.99
    rmsprop_eps: float = 1e-5
    entropy_coef: float = 0.05
    value_coef: float = 0.5
    grad_clip: float = 40.0
    reward_scale: float = 1.0 / 800.0
    reward_alpha: float | None = None
    entropy_coef_final: float | None = 0.005
    return_norm: bool = False
    collision_value: str = "absorbing"
    advantage_norm: bool = False
    episodes_parallel: int = 8
    lr_scale: float = 4.0
    eval_every_steps: int = 20_000
    selection_mode: str = "sampled"
    reward_w_gap: float = -1.0
    reward_w_speed: float = -1.0
    reward_w_accel: float = -0.1
    reward_w_safety: float = -5.0
    reward_w_power: float = -10.0
    power_baseline_kw: float | None = 0.0
    min_active_fraction: float = 0.0

    def __post_init__(self) -> None:
        from infra.limits import check_hidden

        check_hidden(self.hidden)
        if self.n_step < 1 or self.episodes_parallel < 1:
            raise ConfigError("n_step and episodes_parallel must be >= 1")
        if not 0 < self.gamma <= 1:
            raise ConfigError(f"gamma must lie in (0, 1], got {self.gamma}")
        if self.reward_alpha is not None and not 0 <= self.reward_alpha <= 1:
            raise ConfigError(f"reward_alpha must lie in [0, 1], got {self.reward_alpha}")
        if self.entropy_coef_final is not None and self.entropy_coef_final < 0:
            raise ConfigError(f"entropy_coef_final must be >= 0, got {self.entropy_coef_final}")
        for name, allowed in (("collision_value", COLLISION_VALUES),
                              ("selection_mode", EVAL_MODES)):
            if getattr(self, name) not in allowed:
                raise ConfigError(f"{name} must be one of {', '.join(allowed)}, got "
                                  f"{getattr(self, name)!r}")
        for name in ("reward_w_gap", "reward_w_speed", "reward_w_accel", "reward_w_safety",
                     "reward_w_power"):
            if getattr(self, name) > 0:
                raise ConfigError(f"{name} is a cost weight and must be <= 0, got {getattr(self, name)}")
        if self.power_baseline_kw is not None and not math.isfinite(self.power_baseline_kw):
            raise ConfigError(f"power_baseline_kw must be finite, got {self.power_baseline_kw}")
        for name in ("actor_lr", "critic_lr", "reward_scale", "grad_clip", "lr_scale",
                     "rmsprop_eps"):
            if not (math.isfinite(getattr(self, name)) and getattr(self, name) > 0):
                raise ConfigError(f"{name} must be a finite number > 0, got {getattr(self, name)}")
        for name in ("actor_lr", "critic_lr"):  # RMSprop's float32 step: as a shared learner's
            if not self.lr_scale * getattr(self, name) <= 1:
                raise ConfigError(f"{name} x lr_scale is a learning rate and must be <= 1, got "
                                  f"{getattr(self, name)} x {self.lr_scale}")
        if not 0 <= self.rmsprop_alpha < 1:
            raise ConfigError(f"rmsprop_alpha must lie in [0, 1), got {self.rmsprop_alpha}")
        if not 0 <= self.min_active_fraction <= 1:
            raise ConfigError(f"min_active_fraction must lie in [0, 1], got "
                              f"{self.min_active_fraction}")

    #: Published reward sharing (``coop_gamma`` of the published configs) by scenario family
    #: (:func:`envs.scenarios.scenario_family`); other scenarios use :attr:`DEFAULT_REWARD_ALPHA`.
    PUBLISHED_REWARD_ALPHA: ClassVar[dict[str, float]] = {"catchup": 1.0, "slowdown": 0.0}
    DEFAULT_REWARD_ALPHA: ClassVar[float] = 1.0

    def resolved(self, scenario: str | Scenario) -> A2CConfig:
        """This config with ``reward_alpha`` and ``power_baseline_kw`` filled in for
        ``scenario`` (built, or an id; where they were None).

        The config was checked where it was built; the values filled in come from the
        published table and the energy model, so the copy is not checked again."""
        filled: dict[str, float] = {}
        if self.reward_alpha is None or self.power_baseline_kw is None:
            sc = as_scenario(scenario)
            if self.reward_alpha is None:
                family = scenario_family(sc.id)
                filled["reward_alpha"] = self.PUBLISHED_REWARD_ALPHA.get(
                    family, self.DEFAULT_REWARD_ALPHA)
            if self.power_baseline_kw is None:
                from envs.energy import load_power_polynomial

                p0 = load_power_polynomial()(np.array([sc.target_speed_mps]), np.array([0.0]))
                filled["power_baseline_kw"] = round(float(p0[0]), 6)
        if not filled:
            return self
        out = copy.copy(self)  # no __init__: nothing checked twice
        for name, value in filled.items():
            object.__setattr__(out, name, value)
        return out

    def reward_weights(self) -> RewardWeights:
        """The training reward's weights (the benchmark scores with ``RewardWeights()``)."""
        return RewardWeights(gap=self.reward_w_gap, speed=self.reward_w_speed,
                             accel=self.reward_w_accel, safety=self.reward_w_safety,
                             power=self.reward_w_power)

    def entropy_at(self, fraction: float) -> float:
        """Entropy coefficient after ``fraction`` (0..1) of the run."""
        if self.entropy_coef_final is None:
            return self.entropy_coef
        f = min(max(fraction, 0.0), 1.0)
        return self.entropy_coef + (self.entropy_coef_final - self.entropy_coef) * f


# ---------------------------------------------------------------------------- device
def training_device(name: str | torch.device) -> torch.device:
    """The torch device a learner (:class:`marl.a2c.Trainer`) trains on: ``cpu`` (default), ``cuda`` or
    ``cuda:K``. Raises :class:`ConfigError` for another name or a GPU this machine lacks."""
    import torch  # not at the top: the command line reads this module without torch

    try:
        device = torch.device(name)
    except (RuntimeError, TypeError):
        raise ConfigError(f"--device {name!r}: expected cpu, cuda or cuda:K") from None
    if device.type == "cpu":
        return device
    if device.type != "cuda":
        raise ConfigError(f"--device {name}: training runs on cpu or cuda, not {device.type}")
    if not torch.cuda.is_available():
        raise ConfigError(f"--device {name}: this torch ({torch.__version__}) sees no CUDA GPU; "
                          "train on the CPU (--device cpu, the default) or install a CUDA build "
                          "of torch on a GPU machine")
    index = 0 if device.index is None else device.index
    if index >= torch.cuda.device_count():
        raise ConfigError(f"--device {name}: this machine has {torch.cuda.device_count()} CUDA "
                          f"device(s), numbered from 0")
    return torch.device("cuda", index)


# ---------------------------------------------------------------------------- algorithms
def _nothing(*_: object) -> None:
    """No hook."""


class RunState(Protocol):
    """What an algorithm's hooks read and keep of one training run (:class:`marl.a2c.Run` is
    one): its resolved config, its random stream, its agents' rows in the stacked networks, its
    bit tallies and the algorithm's own state between updates."""

    config: A2CConfig
    generator: torch.Generator
    rows: slice
    bits: dict[str, float]
    hook_state: dict[str, Any]


@dataclass
class Algorithm:
    """An algorithm's distinctive parts: its config, its network and what it does around the
    update as plain functions (each algorithm file builds one as its ``ALGORITHM``).

    Attributes
    ----------
    name : str
        Registered name.
    config_cls : type
        Its config, a frozen subclass of :class:`A2CConfig`.
    net_cls : type
        Its network, a subclass of :class:`marl.networks.AgentNet` (:meth:`build_net`).
    setup : callable(run)
        Once per run after the network exists; the run's own state of the algorithm goes into
        ``run.hook_state``.
    before_step : callable(run, net)
        After backward and per-agent clipping, before the optimiser step (e.g. QSGD), on the
        run's rows ``run.rows`` of ``net``.
    after_step : callable(run, net)
        After the optimiser step (e.g. a consensus round), on the run's rows of ``net``.
    """

    name: str
    config_cls: type[A2CConfig]
    net_cls: Callable[..., AgentNet]
    setup: Callable[[RunState], None] = _nothing
    before_step: Callable[[RunState, AgentNet], None] = _nothing
    after_step: Callable[[RunState, AgentNet], None] = _nothing

    def build_net(self, config: A2CConfig, n_agents: int, with_critic: bool = True,
                  generator: torch.Generator | None = None) -> AgentNet:
        """The batched network of ``n_agents`` agents, ``config.hidden`` wide (``with_critic``
        False: the acting part only), its initial weights drawn from ``generator``."""
        return self.net_cls(n_agents, config.hidden, with_critic, generator=generator)


def algorithm(name: str) -> Algorithm:
    """The :class:`Algorithm` of a registered name (module ``marl.<name>``)."""
    if name not in PAPER_ALGORITHMS:
        raise UnknownNameError("algorithm", name, PAPER_ALGORITHMS)
    module = importlib.import_module(f"marl.{name}")
    return module.ALGORITHM


def config_from_dict(algo: Algorithm, values: dict[str, Any]) -> A2CConfig:
    """Rebuild an algorithm's config from a checkpoint's dict (unknown keys are an error)."""
    names = {f.name for f in dataclasses.fields(algo.config_cls)}
    extra = set(values) - names
    if extra:
        raise ConfigError(f"{algo.name} config has no fields {sorted(extra)}")
    return algo.config_cls(**values)


#: The configs chosen by ``cacc-bench tune`` that ship with the package.
TUNED_CONFIGS = Path(__file__).resolve().parent / "tuned_configs.json"


def tuned_options(algo: str, scenario: str, path: Path = TUNED_CONFIGS) -> dict[str, object]:
    """Config overrides chosen by ``cacc-bench tune`` for ``algo`` on ``scenario``."""
    import json

    shown = "the package's marl/tuned_configs.json" if path == TUNED_CONFIGS else str(path)
    if not path.exists():
        raise ConfigError(f"--tuned: {shown} is missing; make it with `cacc-bench tune` and copy "
                          "its tuned_configs.json there")
    try:
        configs = json.loads(path.read_text())["configs"]
    except (ValueError, KeyError) as exc:
        raise ConfigError(f"--tuned: {shown} is not a tuned_configs.json ({exc})") from None
    entry = configs.get(f"{algo}/{scenario}")
    if entry is None:
        have = ", ".join(sorted(configs)) or "none"
        raise ConfigError(f"--tuned: no tuned config for {algo} on {scenario} in {shown} "
                          f"(it has: {have}); run `cacc-bench tune --algos {algo} "
                          f"--scenarios {scenario}`")
    return dict(entry["config"])

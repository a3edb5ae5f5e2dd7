"""Stern et al.'s wave-dampening controllers: ``followerstopper`` and ``pi-saturation``.

Both come from R. E. Stern et al., "Dissipation of stop-and-go waves via control of autonomous
vehicles: Field experiments", Transportation Research Part C 89 (2018) 205-221 (arXiv
1705.01693), where one such vehicle among about 20 human drivers on a ring dissipated the
stop-and-go wave; Flow ships both (``flow/controllers/velocity_controllers.py``, classes
``FollowerStopper`` and ``PISaturation``, flow-project/flow at a511c41c, 2020-12-11). The
equations below are the project's spec of the paper's laws, checked line by line against Flow;
the paper's own text could not be consulted here, so where Flow and the spec differ the choice is
argued from the law itself. Each
computes a *commanded speed* from its own sensors only (gap ``dx`` to the vehicle ahead, own speed
``v``, that vehicle's speed ``v_l``; no V2V, no leader needed, so they run on the ring, where
``PlatoonState.pred_speed_mps`` is the ring predecessor's speed) and, as Flow does, turns it into
the acceleration ``(v_cmd - v) / dt`` (the environment clips it to [-2.5, 2.5] m/s^2).

FollowerStopper (Flow ``velocity_controllers.py`` lines 42-47 and 75-116)
--------------------------------------------------------------------------
With ``dv- = min(v_l - v, 0)`` (only closing in counts) and the switching gaps
``dx_k = dx_k0 + dv-^2 / (2 d_k)``, ``dx_10, dx_20, dx_30 = 4.5, 5.25, 6.0 m``,
``d_1, d_2, d_3 = 1.5, 1.0, 0.5 m/s^2``, and ``v~ = min(max(v_l, 0), U)``::

    v_cmd = 0                                          dx <= dx_1
          = v~ (dx - dx_1) / (dx_2 - dx_1)             dx_1 < dx <= dx_2
          = v~ + (U - v~) (dx - dx_2) / (dx_3 - dx_2)  dx_2 < dx <= dx_3
          = U                                          dx_3 < dx

Flow writes ``U - v`` (the *own* speed) in the third region (line 100); the spec writes the
capped leader speed ``v~`` there, which makes ``v_cmd`` continuous (``v~`` at ``dx_2``, ``U`` at
``dx_3``), while Flow's jumps by ``v~ - v`` at ``dx_3``. We follow the spec's continuous law: the
regions are described as a blend from ``v~`` to ``U``, and Flow's own test
(``tests/fast_tests/test_controllers.py``, ``TestFollowerStopper``) never reaches the third
region, so it does not pin Flow's form down. Flow's safe-velocity fail-safe and its junction
rules are not part of the law and are left out.

The set speed ``U`` (option ``set_speed_mps``) is the driver's choice in the paper. Flow's class
defaults to ``v_des = 15`` m/s and its ring examples do not set one (``examples/exp_configs``
drives the ring with IDM or RL vehicles only; Flow's FollowerStopper test uses 7.5 m/s). 15 m/s is
three times the ring's uniform-flow speed, which turns the law into plain following with the
short gaps ``dx_k`` (no dampening), so our default (None) is the scenario's target speed
``v*``: on ``ring-v1`` the speed of the uniform flow the ring can carry (the IDM equilibrium speed
of its uniform gap, 4.82 m/s on 260 m with 22 vehicles); on the leader scenarios the cruise speed
(15 m/s). On ``ring-v1`` Flow's 15 m/s and 7.5 m/s leave the wave in place (the humans'
speed std stays 1.5-2.9 m/s, ``docs/concepts/controllers.md``); the ring's own speed removes it.

PI with saturation (Flow ``velocity_controllers.py`` lines 185-240)
--------------------------------------------------------------------
``U`` is the mean of the own speed over the last 38 s (380 steps at dt = 0.1 s, the current one
included), and with ``gamma = 2 m``, ``g_l = 7 m``, ``g_u = 30 m``, ``v_catch = 1 m/s``::

    v_target   = U + v_catch min(max((dx - g_l) / (g_u - g_l), 0), 1)
    dx_s       = max(2 (v_l - v), 4)
    alpha      = min(max((dx - dx_s) / gamma, 0), 1),   beta = 1 - alpha / 2
    v_cmd(k+1) = beta (alpha v_target + (1 - alpha) v_l) + (1 - beta) v_cmd(k)

Two details differ from Flow: Flow's speed history stops at 379 samples (it appends, then drops
the oldest once the list *reaches* ``int(38 / dt)``), we keep the 380 samples of 38 s; and Flow
starts the filter at ``v_cmd = 0``, which commands a hard brake at the first step of an episode
begun at speed, while we start it at the own speed of the first step (the controller takes over a
vehicle already moving). The sign in ``dx_s`` is Flow's and the spec's, ``2 (v_l - v)``: the
safety distance grows when the predecessor pulls away, not when closing in; with it, strings made
only of this law collide when the leader brakes hard at 15 m/s (``brake-v1``, ``slowdown-v1``,
``openacc-s-v1``); the law was designed for the ring's low speeds and is kept as published.

Both laws act per seat on its own measurements (elementwise in the batch), so an episode gives the
same run alone or in a batch, to the last bit (``batch_invariant``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from controllers.base import Controller, EpisodeContext
from envs.platoon import PlatoonState
from infra.errors import ConfigError

#: FollowerStopper's switching gaps at zero closing speed (m) and their decelerations (m/s^2).
FS_GAPS_M: tuple[float, float, float] = (4.5, 5.25, 6.0)
FS_DECELS_MPS2: tuple[float, float, float] = (1.5, 1.0, 0.5)


def followerstopper_switch_gaps_m(speed_mps: np.ndarray, pred_speed_mps: np.ndarray,
                                  gaps0_m: tuple[float, float, float] = FS_GAPS_M,
                                  decels_mps2: tuple[float, float, float] = FS_DECELS_MPS2,
                                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The switching gaps ``dx_k = dx_k0 + dv-^2 / (2 d_k)``, ``dv- = min(v_l - v, 0)``.

    Parameters
    ----------
    speed_mps, pred_speed_mps : arrays of one shape
        Own speed ``v`` and the speed ``v_l`` of the vehicle ahead.

    Returns
    -------
    dx_1, dx_2, dx_3 : arrays (m)
    """
    dv_minus = np.minimum(np.asarray(pred_speed_mps, dtype=np.float64) - speed_mps, 0.0)
    sq = dv_minus * dv_minus
    d1, d2, d3 = (g + sq / (2.0 * d) for g, d in zip(gaps0_m, decels_mps2, strict=True))
    return d1, d2, d3


def followerstopper_speed_mps(gap_m: np.ndarray, speed_mps: np.ndarray,
                              pred_speed_mps: np.ndarray, set_speed_mps: float | np.ndarray,
                              ) -> np.ndarray:
    """FollowerStopper's commanded speed (Stern et al. 2018; continuous third region).

    Parameters
    ----------
    gap_m, speed_mps, pred_speed_mps : arrays of one shape
        Gap ``dx`` to the vehicle ahead, own speed ``v``, its speed ``v_l``.
    set_speed_mps : float or array
        The set speed ``U``.

    Returns
    -------
    array
        The commanded speed (m/s), in ``[0, U]``.
    """
    dx = np.asarray(gap_m, dtype=np.float64)
    dx1, dx2, dx3 = followerstopper_switch_gaps_m(speed_mps, pred_speed_mps)
    u = np.broadcast_to(np.asarray(set_speed_mps, dtype=np.float64), dx.shape)
    v_tilde = np.minimum(np.maximum(pred_speed_mps, 0.0), u)
    ramp = v_tilde * (dx - dx1) / (dx2 - dx1)
    blend = v_tilde + (u - v_tilde) * (dx - dx2) / (dx3 - dx2)
    return np.where(dx <= dx1, 0.0, np.where(dx <= dx2, ramp, np.where(dx <= dx3, blend, u)))


@dataclass(frozen=True)
class FollowerStopperConfig:
    """Options of ``followerstopper``.

    Attributes
    ----------
    set_speed_mps : float or None
        The set speed ``U`` (m/s); None: the scenario's target speed (on ``ring-v1`` the IDM
        equilibrium speed of its uniform gap, 4.82 m/s by default).
    """

    set_speed_mps: float | None = None

    def __post_init__(self) -> None:
        if self.set_speed_mps is not None and not 0 < self.set_speed_mps <= 40:
            raise ConfigError(f"followerstopper set_speed_mps must lie in (0, 40] m/s, got "
                              f"{self.set_speed_mps}")


class FollowerStopperController(Controller):
    """Stern et al.'s FollowerStopper on every automated seat (own sensors, no V2V)."""

    name = "followerstopper"
    family = "linear"  # a hand-designed feedback law (piecewise linear in the gap)
    batch_invariant = True
    config_cls = FollowerStopperConfig
    config: FollowerStopperConfig

    def __init__(self, **options: object) -> None:
        super().__init__(**options)
        self.set_speed_mps = 0.0
        self.dt_s = 0.1

    def reset(self, ctx: EpisodeContext) -> None:
        self.dt_s = ctx.params.dt_s
        self.set_speed_mps = (ctx.target_speed_mps if self.config.set_speed_mps is None
                              else self.config.set_speed_mps)

    def act(self, state: PlatoonState, observation: np.ndarray | None) -> np.ndarray:
        v_cmd = followerstopper_speed_mps(state.gap_m, state.speed_mps, state.pred_speed_mps,
                                          self.set_speed_mps)
        return (v_cmd - state.speed_mps) / self.dt_s


#: PI-with-saturation constants (Stern et al. 2018): gamma (m), g_l (m), g_u (m), v_catch (m/s),
#: and the length of the speed average (s).
PI_GAMMA_M = 2.0
PI_GAP_LOW_M = 7.0
PI_GAP_HIGH_M = 30.0
PI_CATCH_MPS = 1.0
PI_WINDOW_S = 38.0


def pi_window_steps(dt_s: float, window_s: float = PI_WINDOW_S) -> int:
    """Samples in the PI controller's speed average: ``round(window / dt)`` (380 at 0.1 s)."""
    return max(1, int(round(window_s / dt_s)))


def pi_saturation_step(gap_m: np.ndarray, speed_mps: np.ndarray, pred_speed_mps: np.ndarray,
                       mean_speed_mps: np.ndarray, prev_command_mps: np.ndarray) -> np.ndarray:
    """One update of the PI-with-saturation commanded speed ``v_cmd(k+1)``.

    Parameters
    ----------
    gap_m, speed_mps, pred_speed_mps : arrays of one shape
        Gap ``dx``, own speed ``v``, speed ``v_l`` of the vehicle ahead.
    mean_speed_mps : array
        ``U``, the mean own speed over the last 38 s.
    prev_command_mps : array
        ``v_cmd(k)``.

    Returns
    -------
    array
        ``v_cmd(k+1) = beta (alpha v_target + (1 - alpha) v_l) + (1 - beta) v_cmd(k)``.
    """
    dx = np.asarray(gap_m, dtype=np.float64)
    v_target = mean_speed_mps + PI_CATCH_MPS * np.clip(
        (dx - PI_GAP_LOW_M) / (PI_GAP_HIGH_M - PI_GAP_LOW_M), 0.0, 1.0)
    dx_s = np.maximum(2.0 * (pred_speed_mps - speed_mps), 4.0)
    alpha = np.clip((dx - dx_s) / PI_GAMMA_M, 0.0, 1.0)
    beta = 1.0 - 0.5 * alpha
    return beta * (alpha * v_target + (1.0 - alpha) * pred_speed_mps) + (1.0 - beta) * \
        prev_command_mps


@dataclass(frozen=True)
class PISaturationConfig:
    """Options of ``pi-saturation``.

    Attributes
    ----------
    window_s : float
        Length of the own-speed average ``U`` (s; the paper's 38 s).
    """

    window_s: float = PI_WINDOW_S

    def __post_init__(self) -> None:
        if not 0 < self.window_s <= 600:
            raise ConfigError(f"pi-saturation window_s must lie in (0, 600] s, got "
                              f"{self.window_s}")


class PISaturationController(Controller):
    """Stern et al.'s PI controller with saturation on every automated seat (no V2V)."""

    name = "pi-saturation"
    family = "linear"  # a hand-designed feedback law (a saturated PI on the speed)
    batch_invariant = True
    config_cls = PISaturationConfig
    config: PISaturationConfig

    def __init__(self, **options: object) -> None:
        super().__init__(**options)
        self.dt_s = 0.1
        self.window = pi_window_steps(self.dt_s, self.config.window_s)
        self._speeds = np.zeros((0, 0, 0))
        self._filled = 0
        self._sum = np.zeros((0, 0))
        self._command = np.zeros((0, 0))

    def reset(self, ctx: EpisodeContext) -> None:
        self.dt_s = ctx.params.dt_s
        self.window = pi_window_steps(self.dt_s, self.config.window_s)
        self._speeds = np.zeros((self.window, ctx.batch_size, ctx.n_vehicles))
        self._sum = np.zeros((ctx.batch_size, ctx.n_vehicles))
        self._filled = 0
        self._command = np.zeros((0, 0))

    def mean_speed_mps(self) -> np.ndarray:
        """``U``: the mean of the own speeds of the last ``window`` steps (fewer at the start),
        kept as a running sum per seat (elementwise, so batch-invariant)."""
        return self._sum / min(self._filled, self.window)

    def act(self, state: PlatoonState, observation: np.ndarray | None) -> np.ndarray:
        v = np.asarray(state.speed_mps, dtype=np.float64)
        slot = self._filled % self.window
        if self._filled >= self.window:  # the oldest sample leaves the window
            self._sum -= self._speeds[slot]
        self._speeds[slot] = v
        self._sum += v
        self._filled += 1
        if self._command.shape != v.shape:  # first step: the filter starts at the own speed
            self._command = v.copy()
        self._command = pi_saturation_step(state.gap_m, v, state.pred_speed_mps,
                                           self.mean_speed_mps(), self._command)
        return (self._command - v) / self.dt_s

"""Controllers others wrote, run inside SUMO as references: SUMO's ``ACC`` and ``CACC``
car-following models and Plexe's ``CC`` model (Ploeg's CACC and the PATH CACC), registered as
``sumo:acc``, ``sumo:cacc``, ``plexe:ploeg`` and ``plexe:path``.

They run with ``--simulator sumo`` only (``runs_in``): the SUMO env
(:class:`envs.sumo.env.SumoPlatoonEnv`) gives the automated seats the model's vehicle type
(:meth:`SumoModelController.sumo_model`) and SUMO computes their speeds; :meth:`act` returns
zeros, which the env does not use (as it does not use the commands of human seats). What Plexe's
controllers receive from other vehicles goes through the run's V2V channels (delay, loss, bit
count), fed into SUMO every step with Plexe's parameters ``ccpsa`` (the vehicle ahead) and
``cclsa`` (the platoon leader), instead of Plexe's auto-feeding; SUMO's ``CACC`` model reads its
leader inside SUMO (no channel of the harness acts on it).

Settings (SUMO's vType attributes and Plexe's parameters, from SUMO's ``MSCFModel_CC``,
``MSCFModel_ACC``, ``MSCFModel_CACC`` and ``CC_Const.h``, release 1.28):

- every model: ``minGap`` the standstill distance (0 for Plexe, whose laws add their own
  spacing to SUMO's gap), ``accel``/``decel``/``emergencyDecel`` the run's command bounds,
  ``maxSpeed`` the run's speed bound, speed mode 0 for Plexe (its laws, not SUMO's safe speed,
  decide; Plexe's own examples do the same), SUMO's default for ``ACC``/``CACC``;
- Plexe: ``lanesCount`` 1, ``ccac`` 4 (Ploeg) or 2 (PATH), ``ccds`` 50 m/s (the cruise
  control's desired speed above every platoon speed, so it never caps the CACC), ``ccumin`` /
  ``ccumax`` the command bounds, ``tauEngine`` the run's actuator lag (Plexe's first-order engine
  model, ``alpha = dt / (tau + dt)``; 0 is no lag);
- Ploeg: ``ploegH`` / ``ploegKp`` / ``ploegKd`` (Plexe's defaults 0.5 s, 0.2, 0.7: the gains of
  our ``cacc``); Plexe fixes the standstill distance at 2 m;
- PATH: ``ccsp`` the constant spacing (default: the scenario's target gap), ``c1``, ``xi``,
  ``omegaN`` (Plexe's defaults 0.5, 1, 0.2 rad/s).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from controllers.base import Controller, EpisodeContext, Message, SpacingPolicy
from envs.platoon import PlatoonState
from envs.sumo.env import ROAD_SPEED_LIMIT_MPS
from envs.sumo.models import SumoModel
from infra import limits
from infra.errors import ConfigError

#: The registered models, by name: (SUMO's carFollowModel, Plexe's controller code or None).
MODELS: dict[str, tuple[str, int | None]] = {
    "sumo:acc": ("ACC", None),
    "sumo:cacc": ("CACC", None),
    "plexe:ploeg": ("CC", 4),
    "plexe:path": ("CC", 2),
}
#: Plexe's cruise-control desired speed (m/s): above every speed of the scenarios.
PLEXE_DESIRED_SPEED_MPS = ROAD_SPEED_LIMIT_MPS
#: Plexe's Ploeg controller fixes its standstill distance (``MSCFModel_CC::_ploeg``).
PLOEG_STANDSTILL_M = 2.0


#: Largest time gap (s) and distance (m) of the models' spacing policies: the one bound of
#: every spacing policy (:data:`infra.limits.MAX_TIME_GAP_S`, :data:`infra.limits.MAX_SPACING_M`).
MAX_TIME_GAP_S = limits.MAX_TIME_GAP_S
MAX_DISTANCE_M = limits.MAX_SPACING_M


def _positive(value: float | None, name: str, allow_zero: bool = False,
              high: float = math.inf) -> None:
    if value is None:
        return
    if not (math.isfinite(value) and (value >= 0 if allow_zero else value > 0)):
        raise ConfigError(f"{name} must be a finite number {'>= 0' if allow_zero else '> 0'}, "
                          f"got {value}")
    if value > high:
        raise ConfigError(f"{name} must be at most {high:g}, got {value:g}")


@dataclass(frozen=True)
class SumoModelConfig:
    """Options of the SUMO and Plexe models (each model reads its own; the others are refused
    where they do not act, :meth:`SumoModelController.__init__`). Time gaps lie in
    ``(0, MAX_TIME_GAP_S]``, distances in ``[0, MAX_DISTANCE_M]``, gains are finite and > 0.

    Attributes
    ----------
    time_gap_s : float or None
        ``sumo:acc``/``sumo:cacc``: the vType's ``tau`` (desired time gap); None: ``(d* - r) /
        v*`` so that the scenario's target gap holds at its target speed.
    standstill_m : float
        ``sumo:acc``/``sumo:cacc``: the vType's ``minGap`` (m).
    ploeg_h_s, ploeg_kp, ploeg_kd : float
        ``plexe:ploeg``: Plexe's ``ploegH``, ``ploegKp``, ``ploegKd``.
    spacing_m : float or None
        ``plexe:path``: the constant spacing ``ccsp`` (m); None: the scenario's target gap.
    c1, xi, omega_n : float
        ``plexe:path``: Plexe's ``c1``, ``xi``, ``omegaN`` (rad/s).
    """

    time_gap_s: float | None = None
    standstill_m: float = 2.0
    ploeg_h_s: float = 0.5
    ploeg_kp: float = 0.2
    ploeg_kd: float = 0.7
    spacing_m: float | None = None
    c1: float = 0.5
    xi: float = 1.0
    omega_n: float = 0.2

    def __post_init__(self) -> None:
        _positive(self.time_gap_s, "time_gap_s", high=MAX_TIME_GAP_S)
        _positive(self.standstill_m, "standstill_m", allow_zero=True, high=MAX_DISTANCE_M)
        _positive(self.ploeg_h_s, "ploeg_h_s", high=MAX_TIME_GAP_S)
        for name in ("ploeg_kp", "ploeg_kd", "omega_n"):
            _positive(getattr(self, name), name)
        _positive(self.spacing_m, "spacing_m", high=MAX_DISTANCE_M)
        if not (math.isfinite(self.c1) and 0 <= self.c1 <= 1):
            raise ConfigError(f"c1 must lie in [0, 1], got {self.c1}")
        if not (math.isfinite(self.xi) and self.xi >= 1):
            raise ConfigError(f"xi must be >= 1 (Plexe's PATH gains take sqrt(xi^2 - 1)), "
                              f"got {self.xi}")


#: The options each model reads.
MODEL_OPTIONS: dict[str, tuple[str, ...]] = {
    "sumo:acc": ("time_gap_s", "standstill_m"),
    "sumo:cacc": ("time_gap_s", "standstill_m"),
    "plexe:ploeg": ("ploeg_h_s", "ploeg_kp", "ploeg_kd"),
    "plexe:path": ("spacing_m", "c1", "xi", "omega_n"),
}


class SumoModelController(Controller):
    """A car-following model of SUMO or Plexe for the automated seats (module docstring).

    Parameters
    ----------
    model : str
        A key of :data:`MODELS`.
    **options
        Fields of :class:`SumoModelConfig` the model reads (:data:`MODEL_OPTIONS`).
    """

    family = "linear"
    runs_in = "sumo"
    config_cls = SumoModelConfig
    config: SumoModelConfig

    def __init__(self, model: str, **options: object) -> None:
        if model not in MODELS:
            raise ConfigError(f"unknown SUMO model {model!r}; the models: {', '.join(MODELS)}")
        foreign = [k for k in options if k not in MODEL_OPTIONS[model]]
        if foreign:
            raise ConfigError(f"{model} has no option {foreign[0]!r}; its options are: "
                              f"{', '.join(MODEL_OPTIONS[model])}")
        self.name = self.model = model
        super().__init__(**options)
        self.needs_leader = model == "plexe:path"
        self.sumo_model: SumoModel | None = None
        self._channels: tuple[Any, ...] = ()
        self._n = 0

    @classmethod
    def options_of(cls, model: str) -> dict[str, Any]:
        """The options ``model`` takes, with their defaults."""
        defaults = SumoModelConfig()
        return {k: getattr(defaults, k) for k in MODEL_OPTIONS[model]}

    @classmethod
    def traits(cls, model: str) -> Any:
        """The class-level traits of ``model`` (for the registry's mixed-traffic lists)."""
        return type(f"{cls.__name__}[{model}]", (), {
            "drives_mixed": True, "needs_leader": model == "plexe:path"})

    # ------------------------------------------------------------------ settings
    def _time_gap_s(self, target_gap_m: float, target_speed_mps: float) -> float:
        cfg = self.config
        if cfg.time_gap_s is not None:
            return cfg.time_gap_s
        return max((target_gap_m - cfg.standstill_m) / target_speed_mps, 0.1)

    def spacing_policy(self, target_gap_m: float, target_speed_mps: float) -> SpacingPolicy:
        """The model's own spacing policy: ``minGap + tau v`` (SUMO's), ``2 m + h v``
        (Plexe's Ploeg) or the constant ``ccsp`` (PATH)."""
        cfg = self.config
        if self.model == "plexe:ploeg":
            return SpacingPolicy(PLOEG_STANDSTILL_M, cfg.ploeg_h_s)
        if self.model == "plexe:path":
            return SpacingPolicy(cfg.spacing_m or target_gap_m, 0.0)
        return SpacingPolicy(cfg.standstill_m, self._time_gap_s(target_gap_m, target_speed_mps))

    def messages(self, ctx: EpisodeContext) -> tuple[Message, ...]:
        """Plexe's data over V2V: the vehicle ahead's speed and commanded acceleration (both
        Plexe controllers), and the leader's (PATH)."""
        if self.model == "plexe:ploeg":
            return (Message("plexe_front", 2, "predecessor"),)
        if self.model == "plexe:path":
            n = ctx.n_vehicles
            return (Message("plexe_front", 2, "predecessor"),
                    Message("plexe_leader", 2, tuple((0, i) for i in range(1, n + 1))))
        return ()

    def reset(self, ctx: EpisodeContext) -> None:
        p, cfg = ctx.params, self.config
        car_follow, code = MODELS[self.model]
        vtype = {"accel": repr(p.accel_max_mps2), "decel": repr(-p.accel_min_mps2),
                 "emergencyDecel": repr(-p.accel_min_mps2), "maxSpeed": repr(p.speed_max_mps)}
        params: dict[str, str] = {}
        speed_mode = None
        if code is None:
            # the type admits the scenario's initial speeds (slowdown-v1 starts at up to 37.5
            # m/s: SUMO refuses a departure above the type's maxSpeed or the road's limit times
            # the speed factor), so the models' desired speed is the road's limit
            vtype["maxSpeed"] = repr(ROAD_SPEED_LIMIT_MPS)
            vtype["minGap"] = repr(cfg.standstill_m)
            vtype["tau"] = repr(self._time_gap_s(ctx.target_gap_m, ctx.target_speed_mps))
        else:
            vtype.update({"minGap": "0", "lanesCount": "1", "tauEngine": repr(p.lag_s),
                          "maxSpeed": repr(ROAD_SPEED_LIMIT_MPS)})
            if self.model == "plexe:ploeg":
                vtype.update({"ploegH": repr(cfg.ploeg_h_s), "ploegKp": repr(cfg.ploeg_kp),
                              "ploegKd": repr(cfg.ploeg_kd)})
            else:
                vtype.update({"c1": repr(cfg.c1), "xi": repr(cfg.xi),
                              "omegaN": repr(cfg.omega_n)})
                params["carFollowModel.ccsp"] = repr(cfg.spacing_m or ctx.target_gap_m)
            params.update({
                "carFollowModel.ccac": str(code), "carFollowModel.ccaf": "0",
                "carFollowModel.ccds": repr(PLEXE_DESIRED_SPEED_MPS),
                "carFollowModel.ccumin": repr(p.accel_min_mps2),
                "carFollowModel.ccumax": repr(p.accel_max_mps2)})
            speed_mode = 0
        self.sumo_model = SumoModel(car_follow, vtype, params, speed_mode)
        self._channels = tuple(ctx.channel(m.name) for m in self.messages(ctx))
        self._n = ctx.n_vehicles
        self._dt_s = p.dt_s

    def act(self, state: PlatoonState, observation: np.ndarray | None) -> np.ndarray:
        """Feed Plexe's models what they hear over V2V this step; zeros (SUMO's models drive
        the automated seats; the env does not use these commands)."""
        b, n = state.speed_mps.shape
        if self._channels:
            self._feed(state)
        return np.zeros((b, n))

    def _feed(self, state: PlatoonState) -> None:
        """Send every vehicle's speed and its command over the last step through the channels,
        then set what each automated follower holds as Plexe's ``ccpsa`` (and ``cclsa``).

        The leader's command over the last step is its planned acceleration then; a
        follower's is Plexe's ``controllerAcceleration`` of that step (``ccsa``, which Plexe
        prints with 6 significant digits). A message sent at step k is used at step k + 1 +
        delay, the timing of our ``cacc`` (:mod:`controllers.linear`)."""
        import libsumo

        from envs.sumo.env import active_env

        env = active_env()
        b, n = state.speed_mps.shape
        t = state.step
        payload = np.zeros((b, n + 1, 2))
        payload[:, 0, 0] = state.leader_speed_now_mps
        if t > 0 and not state.ring:
            payload[:, 0, 1] = (state.leader_speed_mps[:, t] - state.leader_speed_mps[:, t - 1]) \
                / self._dt_s
        payload[:, 1:, 0] = state.speed_mps
        automated = np.flatnonzero(state.automated_mask)
        live = np.flatnonzero(env.live)
        get = libsumo.vehicle.getParameter
        for k in live:
            for i in automated:
                fields = get(env.vehicle_ids(int(k))[i + 1], "carFollowModel.ccsa").split(":")
                payload[k, i + 1, 1] = float(fields[2])
        heard = [ch.transmit(payload) for ch in self._channels]  # (B, N, 2) each
        time_s = libsumo.simulation.getTime()
        put = libsumo.vehicle.setParameter
        keys = ("carFollowModel.ccpsa", "carFollowModel.cclsa")
        for k in live:
            ids = env.vehicle_ids(int(k))
            for i in automated:
                for key, held in zip(keys, heard, strict=False):
                    speed, u = float(held[k, i, 0]), float(held[k, i, 1])
                    put(ids[i + 1], key,
                        f"{speed!r}:{u!r}:0:0:{time_s!r}:{u!r}:0:0:0")

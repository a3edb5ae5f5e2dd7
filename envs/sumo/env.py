"""The platoon env with SUMO as its simulator: :class:`SumoPlatoonEnv`.

It is the built-in env (:class:`envs.platoon.PlatoonEnv`) with one thing replaced: the physics
step. Observations, rewards, the battery power, the collision rule, the V2V channels and the
frozen ends of episodes stay the built-in env's own code; the new state after each step is read
from SUMO. Settings (``docs/sumo/index.md`` gives their reasons):

- step length 0.1 s (``--step-length``, the env's ``dt_s``); the position update is SUMO's
  ballistic one (``--step-method.ballistic true``: ``x += dt (v + v') / 2``, the built-in env's
  trapezoidal gap update), or, with ``integration="euler"``, SUMO's default semi-implicit Euler
  (``x += dt v'``) for measuring what that default changes;
- the leader and every automated seat a cacc-bench controller commands: speed mode 0 (SUMO's
  safe speed, acceleration and deceleration limits and right-of-way checks off) and
  ``vehicle.setSpeed(v + a dt)`` every step, with ``a`` the command clipped to the bounds and
  passed through the run's actuator lag by the same first-order filter as the built-in env
  (SUMO itself has no actuator lag), the speed clipped to ``[0, speed_max]``;
- human seats: SUMO's own ``IDM`` with the scenario's human parameters (``envs.humans.IDMParams``:
  ``accel`` a, ``decel`` b, ``tau`` T, ``minGap`` s0, ``delta``, desired speed through the lane's
  speed limit), one internal step per step (``stepping`` 0.25 s gives ``int(0.1 / 0.25 + 0.5)``
  = 0, raised to 1 by SUMO), ``emergencyDecel`` at the env's braking bound;
- automated seats of a controller that runs inside SUMO (:class:`envs.sumo.models.SumoModel`):
  SUMO's model drives them, the commands the controller returns are not used;
- collisions: SUMO's own collision handling off (``--collision.action none``); the env's rule
  (a gap below ``gap_min_m``) ends the episode, as in the built-in env, and its vehicles are
  removed from SUMO.

The ``B`` episodes of a batch run on ``B`` separate roads (or rings) of one SUMO simulation
(:mod:`envs.sumo.network`); libsumo holds one simulation per process, so the env that resets
last is the one that runs (:func:`active_env`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from envs.humans import IDMParams
from envs.params import PlatoonParams
from envs.platoon import PlatoonEnv
from envs.scenarios import RING_VEHICLE_LENGTH_M, Scenario
from envs.sumo.models import SumoModel
from envs.sumo.network import network, ring_edges, road_edge, sumo_home, work_folder
from infra.errors import ConfigError

#: The position updates the env can ask SUMO for, the matched one first.
INTEGRATIONS: tuple[str, ...] = ("ballistic", "euler")
#: Vehicle length in SUMO (m): the ring's (Flow's and SUMO's passenger default); gaps are
#: bumper to bumper, so on a straight road the length changes nothing.
VEHICLE_LENGTH_M = RING_VEHICLE_LENGTH_M
#: Speed limit of the roads (m/s): above every speed of the scenarios (slowdown-v1 starts at up
#: to 37.5 m/s), so only the humans' desired speed (their type's ``maxSpeed``) binds.
ROAD_SPEED_LIMIT_MPS = 50.0
#: Road beyond the distance the leader can drive in an episode (m).
ROAD_MARGIN_M = 200.0

_active: SumoPlatoonEnv | None = None


def active_env() -> SumoPlatoonEnv:
    """The SUMO env whose simulation libsumo is running in this process (the last one reset).

    Raises
    ------
    RuntimeError
        When no SUMO env has been reset in this process.
    """
    if _active is None:
        raise RuntimeError("no SUMO simulation is running: reset a SumoPlatoonEnv first")
    return _active


def vehicle_id(episode: int, index: int) -> str:
    """SUMO's id of vehicle ``index`` (0 the leader, 1..N the followers) of episode ``episode``
    of the batch."""
    return f"{episode}.{index}"


def check_sumo_setting(scenario: Scenario, n_vehicles: int, params: PlatoonParams) -> None:
    """Refuse (:class:`ConfigError`, naming what runs) a setting the SUMO backend does not
    simulate: human seats whose model SUMO has no counterpart for (``ovm``), a reaction delay,
    the humans' per-step Gaussian noise (SUMO's IDM draws none), a heterogeneous string."""
    who = scenario.label or scenario.id
    arrangement = scenario.arrangement(n_vehicles)
    if not arrangement.homogeneous:
        if arrangement.human_model != "idm":
            raise ConfigError(f"{who}: the SUMO backend drives human seats with SUMO's IDM; "
                              f"it has no {arrangement.human_model} model: use human_model=idm")
        if arrangement.reaction_delay_s > 0:
            raise ConfigError(f"{who}: SUMO's IDM has no reaction delay; leave reaction_delay_s "
                              "out with --simulator sumo")
        if arrangement.noise_std_mps2 > 0:
            raise ConfigError(f"{who}: SUMO's IDM draws no acceleration noise; add "
                              "human_noise_mps2=0 to the scenario with --simulator sumo "
                              f"({scenario.id}:human_noise_mps2=0)")
    if scenario.vehicle_arrays(n_vehicles, params) is not None:
        raise ConfigError(f"{who}: the SUMO backend runs the published platoon's one vehicle "
                          "class; heterogeneous strings run in the built-in simulator")


class SumoPlatoonEnv(PlatoonEnv):
    """:class:`envs.platoon.PlatoonEnv` with SUMO as its physics (module docstring).

    Parameters
    ----------
    scenario, n_vehicles, params, **kwargs
        As :class:`envs.platoon.PlatoonEnv`.
    integration : {"ballistic", "euler"}
        SUMO's position update (ballistic matches the built-in env).
    idm : IDMParams
        The human seats' IDM parameters.

    Raises
    ------
    ConfigError
        For a setting SUMO does not simulate (:func:`check_sumo_setting`) or an unknown
        ``integration``.
    """

    def __init__(self, scenario: Scenario | str, n_vehicles: int = 8,
                 params: PlatoonParams = PlatoonParams(), *, integration: str = "ballistic",
                 idm: IDMParams = IDMParams(), **kwargs: Any) -> None:
        from envs.sumo import require_sumo

        require_sumo()
        super().__init__(scenario, n_vehicles, params, **kwargs)
        if integration not in INTEGRATIONS:
            raise ConfigError(f"integration must be one of {', '.join(INTEGRATIONS)}, "
                              f"got {integration!r}")
        check_sumo_setting(self.scenario, self.n_vehicles, params)
        self.integration = integration
        self.idm = idm
        self.model: SumoModel | None = None
        self._ids: list[list[str]] = []
        self._x0 = np.zeros((0, 0))
        self._live = np.zeros(0, dtype=bool)
        self._commanded = np.zeros(0, dtype=bool)
        self._ring_length_m = 0.0

    def bind_controller(self, controller: Any) -> None:
        """Take the SUMO model of a controller that runs inside SUMO (its ``sumo_model``
        attribute, a :class:`envs.sumo.models.SumoModel`), or None for one that commands."""
        self.model = getattr(controller, "sumo_model", None)

    @property
    def live(self) -> np.ndarray:
        """``(B,)`` booleans: the episodes whose vehicles are in SUMO (not ended)."""
        return self._live

    def vehicle_ids(self, episode: int) -> list[str]:
        """SUMO's ids of episode ``episode``'s vehicles, the leader first (on a ring, whose
        leader is not there, index 0 names no vehicle)."""
        return self._ids[episode]

    # ------------------------------------------------------------------ episodes
    def reset(self, seeds: Sequence[int] | np.ndarray | int,
              perturbation: float | Sequence[float] | np.ndarray | None = None
              ) -> np.ndarray | None:
        """Start one episode per seed (:meth:`envs.platoon.PlatoonEnv.reset`) and a SUMO
        simulation holding them, each on its own road."""
        global _active
        obs = super().reset(seeds, perturbation)
        self._humans = None  # SUMO's IDM drives the human seats
        s = self.state
        assert s is not None
        b, n = s.gap_m.shape
        automated = s.automated_mask
        #: the seats the env commands by setSpeed (the others: SUMO's models)
        self._commanded = automated & (self.model is None)
        ring = s.ring
        length = VEHICLE_LENGTH_M
        # positions along each road (x: front bumper), the leader at index 0: x_N = 0, upwards
        # to x_1 and the leader (on a ring, follower 1 is behind follower N and there is no leader)
        x0 = np.zeros((b, n + 1))
        for i in range(n - 1, 0 if ring else -1, -1):
            x0[:, i] = x0[:, i + 1] + s.gap_m[:, i] + length
        if ring:
            self._ring_length_m = float(self.scenario.options["length_m"])
            x0[:, 0] = np.nan
            road_m = self._ring_length_m
        else:
            travel = float(np.max(s.leader_speed_mps.sum(axis=1)) * self.params.dt_s)
            road_m = 1000.0 * math.ceil((float(x0.max()) + travel + ROAD_MARGIN_M) / 1000.0)
        self._x0 = x0
        kind = "ring" if ring else "road"
        net = network(kind, b, road_m, ROAD_SPEED_LIMIT_MPS)
        routes = self._write_routes(road_m, x0, automated)
        self._start(net, routes)
        self._ids = [[vehicle_id(k, i) for i in range(n + 1)] for k in range(b)]
        import libsumo

        expected = b * (n if ring else n + 1)
        if libsumo.vehicle.getIDCount() != expected:
            raise RuntimeError(f"SUMO inserted {libsumo.vehicle.getIDCount()} of {expected} "
                               "vehicles")
        for k in range(b):
            if not ring:
                libsumo.vehicle.setSpeedMode(self._ids[k][0], 0)
            for i in range(n):
                vid = self._ids[k][i + 1]
                if self._commanded[i]:
                    libsumo.vehicle.setSpeedMode(vid, 0)
                elif automated[i] and self.model is not None:
                    if self.model.speed_mode is not None:
                        libsumo.vehicle.setSpeedMode(vid, self.model.speed_mode)
                    # the env's speed bound, as for commanded seats (inserted above it, as
                    # slowdown-v1's followers, SUMO brings the speed down at the first step);
                    # first: it gives the vehicle a type of its own
                    libsumo.vehicle.setMaxSpeed(vid, self.params.speed_max_mps)
                    for key, value in self.model.vehicle_parameters.items():
                        libsumo.vehicle.setParameter(vid, key, value)
        self._live = np.ones(b, dtype=bool)
        _active = self
        return obs

    def _write_routes(self, road_m: float, x0: np.ndarray, automated: np.ndarray) -> str:
        """The route file of the batch's vehicles at their initial positions and speeds."""
        s = self.state
        assert s is not None
        b, n = s.gap_m.shape
        p, idm, length = self.params, self.idm, VEHICLE_LENGTH_M
        shared = {"length": repr(length), "sigma": "0", "speedFactor": "1", "speedDev": "0",
                  "lcStrategic": "-1", "lcCooperative": "0", "lcSpeedGain": "0",
                  "lcKeepRight": "0"}
        common = " ".join(f'{k}="{v}"' for k, v in shared.items())
        types = [
            # commanded by setSpeed with speed mode 0: its limits never act
            f'<vType id="cmd" {common} minGap="0" maxSpeed="{ROAD_SPEED_LIMIT_MPS!r}" '
            'accel="100" decel="100" emergencyDecel="100"/>',
            f'<vType id="human" {common} carFollowModel="IDM" accel="{idm.accel_max_mps2!r}" '
            f'decel="{idm.decel_comfort_mps2!r}" emergencyDecel="{-p.accel_min_mps2!r}" '
            f'tau="{idm.time_gap_s!r}" minGap="{idm.standstill_m!r}" delta="{idm.delta!r}" '
            f'maxSpeed="{idm.desired_speed_mps!r}" stepping="0.25"/>',
        ]
        if self.model is not None:
            attrs = " ".join(f'{k}="{v}"' for k, v in {**shared, **self.model.vtype}.items())
            types.append(f'<vType id="model" carFollowModel='
                         f'"{self.model.car_follow_model}" {attrs}/>')
        lines = ["<routes>", *types]
        ring = s.ring
        speeds = np.concatenate([s.leader_speed_mps[:, :1], s.speed_mps], axis=1)
        for k in range(b):
            if ring:
                edges = ring_edges(k)
                laps = int(math.ceil(ROAD_SPEED_LIMIT_MPS * self.n_steps * p.dt_s / road_m)) + 2
                quarter = road_m / len(edges)
            for i in range(0 if not ring else 1, n + 1):
                vtype = ("cmd" if i == 0 or self._commanded[i - 1]
                         else "model" if automated[i - 1] else "human")
                if ring:
                    j = min(int(x0[k, i] // quarter), len(edges) - 1)
                    route = " ".join(edges[j:] + edges * laps)
                    pos = float(x0[k, i] - j * quarter)
                else:
                    route = road_edge(k)
                    pos = float(x0[k, i])
                rid = f"route{k}.{i}"
                lines.append(f'<route id="{rid}" edges="{route}"/>')
                lines.append(
                    f'<vehicle id="{vehicle_id(k, i)}" type="{vtype}" route="{rid}" depart="0" '
                    f'departLane="0" departPos="{pos!r}" departSpeed="{float(speeds[k, i])!r}" '
                    'insertionChecks="none"/>')
        lines.append("</routes>")
        path = work_folder() / "batch.rou.xml"
        path.write_text("\n".join(lines) + "\n")
        return str(path)

    def _start(self, net: Any, routes: str) -> None:
        """(Re)load SUMO with the network and routes, and step once to insert the vehicles."""
        import libsumo

        sumo_home()
        args = ["-n", str(net), "-r", routes, "--step-length", repr(self.params.dt_s),
                "--step-method.ballistic", "true" if self.integration == "ballistic" else "false",
                "--collision.action", "none", "--collision.check-junctions", "false",
                "--time-to-teleport", "-1", "--no-step-log", "true", "--no-warnings", "true",
                "--duration-log.disable", "true", "--seed", "0", "--begin", "0"]
        if libsumo.isLoaded():
            libsumo.load(args)
        else:
            libsumo.start(["sumo", *args])
        libsumo.simulationStep()  # inserts every vehicle at its position and speed

    def close(self) -> None:
        """End the SUMO simulation of this env (if it is the running one)."""
        global _active
        if _active is self:
            import libsumo

            if libsumo.isLoaded():
                libsumo.close()
            _active = None

    # ------------------------------------------------------------------ the step
    def _physics(self, gap_m: np.ndarray, speed_mps: np.ndarray, realised_accel_mps2: np.ndarray,
                 command_mps2: np.ndarray, leader_speed_mps: np.ndarray,
                 leader_speed_next_mps: np.ndarray, params: PlatoonParams = PlatoonParams(),
                 ring: bool = False, vehicles: Any = None
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """One step in SUMO (the signature of :func:`envs.dynamics.physics_step`)."""
        import libsumo

        dt = params.dt_s
        u = np.clip(command_mps2, params.accel_min_mps2, params.accel_max_mps2)
        a = realised_accel_mps2 + (u - realised_accel_mps2) * params.lag_gain \
            if params.lag_s > 0 else u
        v_cmd = np.clip(speed_mps + a * dt, 0.0, params.speed_max_mps)
        set_speed = libsumo.vehicle.setSpeed
        commanded = np.flatnonzero(self._commanded)
        live = np.flatnonzero(self._live)
        for k in live:
            ids = self._ids[k]
            if not ring:
                set_speed(ids[0], float(leader_speed_next_mps[k]))
            for i in commanded:
                set_speed(ids[i + 1], float(v_cmd[k, i]))
        libsumo.simulationStep()
        get_speed, get_distance = libsumo.vehicle.getSpeed, libsumo.vehicle.getDistance
        b, n = speed_mps.shape
        v_next = np.array(speed_mps, dtype=np.float64, order="F")
        gap_next = np.array(gap_m, dtype=np.float64, order="F")
        first = 1 if ring else 0
        for k in live:
            ids = self._ids[k]
            x = np.array([get_distance(ids[i]) for i in range(first, n + 1)]) + self._x0[k, first:]
            v = np.array([get_speed(ids[i]) for i in range(1, n + 1)])
            v_next[k] = v
            if ring:
                gap_next[k, 1:] = x[:-1] - x[1:] - VEHICLE_LENGTH_M
                gap_next[k, 0] = x[-1] + self._ring_length_m - x[0] - VEHICLE_LENGTH_M
            else:
                gap_next[k] = x[:-1] - x[1:] - VEHICLE_LENGTH_M
        applied = (v_next - speed_mps) * (1.0 / dt)
        realised = np.where(self._commanded[None, :], a, applied)
        return gap_next, v_next, realised, applied

    def _advance(self, s: Any, command_mps2: np.ndarray) -> Any:
        """The built-in env's step with SUMO's physics; the vehicles of an episode that ended
        are removed from SUMO."""
        result = super()._advance(s, command_mps2)
        ended = np.flatnonzero(self._live & s.done)
        if ended.size:
            import libsumo

            for k in ended:
                for vid in self._ids[k]:
                    if vid in libsumo.vehicle.getIDList():
                        libsumo.vehicle.remove(vid)
            self._live[ended] = False
        return result

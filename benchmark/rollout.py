"""The closed loop: the only place where a controller's ``act`` and the env's ``step`` alternate."""

from __future__ import annotations

import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np

from controllers.base import Controller, EpisodeContext, reset_controller
from envs.channel import ChannelConfig
from envs.params import PlatoonParams
from envs.platoon import PlatoonEnv
from envs.scenarios import Scenario
from infra.errors import ControllerContractError
from infra.interrupt import raise_if_interrupted


@dataclass
class Trajectory:
    """Everything a run produced, for one episode (``T`` steps taken, ``N`` followers).

    Row 0 of the state arrays is the initial state; row ``t`` the state after step ``t``.

    Attributes
    ----------
    gap_m, speed_mps : (T+1, N)
    accel_mps2 : (T+1, N)
        Applied acceleration of the step that led to the row (0 at row 0).
    power_kw : (T+1, N)
        Battery power over that step (0 at row 0).
    leader_speed_mps, leader_accel_mps2 : (T+1,)
    reward, tracking_reward : (T,)
        Sum over agents of the evaluation reward with and without the power term.
    command_mps2 : (T, N)
        What the controller's ``act`` returned at each step, before the env's bounds and lag
        (for a recorded platoon, the recorded acceleration).
    compute_s : (T,)
        Wall time of each ``act`` call (the whole platoon).
    collided : bool
    steps : int
    bits_sent : int
    solver_failures : int
    safety_interventions : int
        Follower-steps whose command a safety filter lowered (0 without one, see
        :meth:`controllers.base.Controller.intervention_totals`).
    safety_correction_mps2 : float
        Sum over those follower-steps of how much it lowered the applied command (m/s^2).
    automated : (N,) bool or None
        The seats the controller commanded (False: a human seat driven by the env,
        :mod:`envs.humans`); None reads as every seat automated (the published platoon).
    settle_steps : int
        Steps left out of the mixed-traffic metrics at the start (the scenario's ``settle_s``
        in steps: 600 on ``ring-v1``, 0 elsewhere); they use rows ``settle_steps + 1 .. T``.
    ring : bool
        A ring road: there is no leader and ``leader_speed_mps`` records follower N's speed
        (follower 1's predecessor).
    vehicle_classes : tuple of str or None
        The followers' vehicle classes (:mod:`envs.vehicle_classes`), follower 1 first; None:
        the homogeneous platoon.
    drag_saving : str
        The platoon drag-saving model the power used (scenario option ``drag_saving``).
    """

    gap_m: np.ndarray
    speed_mps: np.ndarray
    accel_mps2: np.ndarray
    power_kw: np.ndarray
    leader_speed_mps: np.ndarray
    leader_accel_mps2: np.ndarray
    reward: np.ndarray
    tracking_reward: np.ndarray
    command_mps2: np.ndarray
    compute_s: np.ndarray
    collided: bool
    steps: int
    bits_sent: int
    solver_failures: int
    dt_s: float
    safety_interventions: int = 0
    safety_correction_mps2: float = 0.0
    automated: np.ndarray | None = None
    settle_steps: int = 0
    ring: bool = False
    vehicle_classes: tuple[str, ...] | None = None
    drag_saving: str = "none"


def rollout(
    controller: Controller,
    scenario: Scenario,
    n_vehicles: int,
    seed: int,
    params: PlatoonParams = PlatoonParams(),
    channel: ChannelConfig = ChannelConfig(),
    simulator: str = "builtin",
) -> Trajectory:
    """Run one episode of ``scenario`` with ``controller`` until its end or a collision.

    The reward of each step is the environment's own (evaluation form: no safety term; the
    tracking reward is the same without the power term), so metrics never recompute it.
    ``simulator`` is ``builtin`` or ``sumo`` (:mod:`envs.simulators`).
    """
    return rollout_batch(controller, scenario, n_vehicles, [seed], params, channel,
                         simulator)[0]


def rollout_batch(
    controller: Controller,
    scenario: Scenario,
    n_vehicles: int,
    seeds: Sequence[int],
    params: PlatoonParams = PlatoonParams(),
    channel: ChannelConfig = ChannelConfig(),
    simulator: str = "builtin",
) -> list[Trajectory]:
    """Run the episodes of ``seeds`` together (one batched env, one controller reset).

    Each episode runs to its end or its collision; an episode that ended is frozen by the env
    while the others go on, and its trajectory stops at its own last step. With one seed this is
    :func:`rollout`. Every episode depends only on its own seed (the env, the channels and the
    sampled policies draw from per-episode streams), so an episode gives the same trajectory
    alone or in a batch; for a controller that is ``batch_invariant``, to the last bit.
    ``compute_s`` and ``bits_sent`` of each episode are its share (1/B) of the batch's, counted
    while the episode runs, and ``solver_failures`` is the batch's; with one seed all are exact.
    """
    seeds_arr = np.asarray(list(seeds), dtype=np.int64)
    b = len(seeds_arr)
    if b == 0:
        return []
    from envs.simulators import check_runs_in

    check_runs_in(controller, simulator)  # a model that runs inside one simulator only
    if simulator == "builtin":
        env = PlatoonEnv(scenario, n_vehicles, params, observe=controller.needs_observation)
    else:
        from envs.simulators import make_env

        env = make_env(simulator, scenario, n_vehicles, params,
                       observe=controller.needs_observation)
    recorded = getattr(controller, "recorded", None)
    if recorded is not None:  # a recorded platoon (real data), scored by the same rules
        return [_score_recorded(env, recorded(scenario, n_vehicles), params) for _ in seeds_arr]
    ctx = EpisodeContext(scenario, n_vehicles, seeds_arr, params, channel,
                         closed_loop=rollout_batch)
    with _controller_code(controller, "reset"):
        reset_controller(controller, ctx)
    bind = getattr(env, "bind_controller", None)  # another simulator's env
    if bind is not None:
        bind(controller)
    obs = env.reset(seeds_arr)
    s = env.state
    assert s is not None
    t_max = env.n_steps
    gap = np.zeros((t_max + 1, b, n_vehicles))
    speed = np.zeros_like(gap)
    accel = np.zeros_like(gap)
    power = np.zeros_like(gap)
    reward = np.zeros((t_max, b))
    tracking = np.zeros((t_max, b))
    commands = np.zeros((t_max, b, n_vehicles))
    compute = np.zeros(t_max)
    bits = np.zeros(t_max, dtype=np.int64)
    steps = np.full(b, t_max)
    gap[0], speed[0] = s.gap_m, s.speed_mps
    t = 0
    clock = time.perf_counter
    while t < t_max:
        bits_before = ctx.bits_sent
        t0 = clock()
        with _controller_code(controller, "act"):
            command = controller.act(s, obs)
        compute[t] = (clock() - t0) / b
        # a signal whose exception a library swallowed inside act (measured: about 1 in 8
        # SIGINTs during CasADi MPC sweeps) still ends the run here, unstored
        raise_if_interrupted()
        _check_command(controller, command, b, n_vehicles)
        _check_sent(controller, ctx, t + 1)
        bits[t] = (ctx.bits_sent - bits_before) // b
        was_done = s.done.copy()
        commands[t] = command
        res = env.step(command)
        t += 1
        gap[t], speed[t] = s.gap_m, s.speed_mps
        accel[t], power[t] = res.applied_accel_mps2, res.power_kw
        # C order: a row's sum over agents must not depend on the batch (a Fortran-ordered
        # (B, N) array would be summed in another order than a lone episode's row)
        reward[t - 1] = np.ascontiguousarray(res.reward).sum(axis=1)
        tracking[t - 1] = np.ascontiguousarray(res.tracking_reward).sum(axis=1)
        steps[res.done & ~was_done] = t
        obs = res.observation
        if res.done.all():
            break
    totals_of = getattr(controller, "intervention_totals", None)  # a safety filter's counts
    totals = totals_of() if totals_of is not None else None
    automated = s.automated_mask.copy()
    settle = settle_steps(scenario, params)
    vehicles = getattr(env, "vehicles", None)
    classes = vehicles.names if vehicles is not None else None
    out = []
    for k in range(b):
        n_k = int(steps[k])
        lead = s.leader_speed_mps[k, : n_k + 1]
        lead_accel = np.zeros(n_k + 1)
        lead_accel[1:] = np.diff(lead) / params.dt_s
        c = np.ascontiguousarray  # an episode's arrays, laid out as if it had run alone
        out.append(
            Trajectory(
                gap_m=c(gap[: n_k + 1, k]),
                speed_mps=c(speed[: n_k + 1, k]),
                accel_mps2=c(accel[: n_k + 1, k]),
                power_kw=c(power[: n_k + 1, k]),
                leader_speed_mps=lead,
                leader_accel_mps2=lead_accel,
                reward=c(reward[:n_k, k]),
                tracking_reward=c(tracking[:n_k, k]),
                command_mps2=c(commands[:n_k, k]),
                compute_s=compute[:n_k],
                collided=bool(s.collided[k]),
                steps=n_k,
                bits_sent=int(bits[:n_k].sum()),
                solver_failures=int(getattr(controller, "solver_failures", 0)),
                dt_s=params.dt_s,
                safety_interventions=int(totals[0][k]) if totals is not None else 0,
                safety_correction_mps2=float(totals[1][k]) if totals is not None else 0.0,
                automated=automated.copy(),
                settle_steps=settle,
                ring=bool(scenario.ring),
                vehicle_classes=classes,
                drag_saving=str(scenario.options.get("drag_saving", "none")),
            )
        )
    return out


#: Steps of the episode :func:`check_contract` runs before a command's work (1 s at 0.1 s).
CONTRACT_CHECK_STEPS = 10


def check_contract(controller: Controller, scenario: Scenario, n_vehicles: int,
                   params: PlatoonParams = PlatoonParams(),
                   channel: ChannelConfig = ChannelConfig(),
                   steps: int = CONTRACT_CHECK_STEPS) -> None:
    """Refuse, before a command's work, a controller that breaks the loop's contract at once:
    run the first ``steps`` steps of one episode (seed 0) of ``scenario`` through
    :func:`rollout`; a command of the wrong shape, type or not finite, or an error its own code
    raises, is a :class:`ConfigError` naming the controller and what it broke.

    For the commands whose work is one measurement of a controller rather than stored runs
    (``stability --empirical``, ``perf``): ``run`` stores such a failure as the run's.

    Parameters
    ----------
    controller : Controller
        A fresh controller (the check resets it).
    scenario : Scenario
        The scenario the work runs on; its first ``steps`` steps are run.
    n_vehicles : int
        Followers N.
    params, channel
        The physical parameters and the V2V channel of the work.
    steps : int
        Steps to run (:data:`CONTRACT_CHECK_STEPS`).

    Raises
    ------
    ConfigError
        ``<name>: act returned a non-finite command; ...`` and the like, or ``controller
        <name> failed in its first steps on <scenario> (RuntimeError: ...)``.
    """
    import dataclasses

    from infra.errors import CaccBenchError, ConfigError
    from infra.plugins import first_line

    short = dataclasses.replace(scenario, n_steps=min(steps, scenario.n_steps))
    try:
        rollout(controller, short, n_vehicles, 0, params, channel)
    except CaccBenchError:
        raise
    except ControllerContractError as exc:
        raise ConfigError(f"{exc}; fix the controller (its contract: "
                          "controllers.base.Controller)") from None
    except Exception as exc:  # noqa: BLE001 - the controller's own code: one line, not its trace
        raise_if_interrupted()
        raise ConfigError(f"controller {controller.name} failed in its first {steps} steps on "
                          f"{scenario.label or scenario.id} ({first_line(exc)}); fix the "
                          "controller (`cacc-bench run` with it stores each failure's traceback "
                          "in its runs)") from None


def settle_steps(scenario: Scenario, params: PlatoonParams) -> int:
    """The scenario's ``settle_s`` in whole steps of ``params.dt_s`` (rounded)."""
    return int(round(scenario.settle_s / params.dt_s))


@contextmanager
def _controller_code(controller: Controller, method: str) -> Iterator[None]:
    """Around a call of the controller's own code (``reset``, ``act``): ``sys.exit()`` there
    (a user's controller, :mod:`infra.plugins`) is the run's failure, a
    :class:`ControllerContractError`, not the end of the command that runs it; a signal
    received meanwhile still ends the command (:func:`raise_if_interrupted`)."""
    try:
        yield
    except SystemExit as exc:
        raise_if_interrupted()
        raise ControllerContractError(
            f"{controller.name}: {method} called sys.exit({exc.code!r}); a controller reports "
            "a failure by raising an exception, never by ending the process") from None


def _check_command(controller: Controller, command: np.ndarray, b: int, n: int) -> None:
    """The loop's contract: ``act`` returns ``(B, N)`` finite accelerations (real numbers)."""
    shape = np.shape(command)
    if shape != (b, n):
        raise ControllerContractError(
            f"{controller.name}: act returned shape {shape}, expected (B, N) = ({b}, {n})")
    kind = np.asarray(command).dtype
    if kind.kind not in "fiu":  # strings, objects, booleans, complex numbers
        raise ControllerContractError(
            f"{controller.name}: act returned values of dtype {kind}, expected (B, N) = "
            f"({b}, {n}) accelerations as real numbers (float)")
    if not np.all(np.isfinite(command)):
        raise ControllerContractError(f"{controller.name}: act returned a non-finite command")


def _check_sent(controller: Controller, ctx: EpisodeContext, steps: int) -> None:
    """The channel contract: the channel of every declared message sends once per step, so what
    the controller uses at a step went through the run's delay and loss and was counted."""
    for ch in ctx.channels.values():
        if ch.transmissions != steps:
            raise ControllerContractError(
                f"{controller.name}: its channel {ch.name!r} sent {ch.transmissions} times in "
                f"{steps} steps; every declared message is sent once per act")


def _score_recorded(env: PlatoonEnv, rec: dict[str, np.ndarray], params: PlatoonParams) -> Trajectory:
    """A :class:`Trajectory` of a recorded platoon, with the env's power and reward."""
    gap, speed, accel = rec["gap_m"], rec["speed_mps"], rec["accel_mps2"]
    power_after, reward, tracking, collided = env.score_recorded(gap[1:], speed[1:], accel[1:])
    hit = np.flatnonzero(collided)
    steps = int(hit[0]) + 1 if hit.size else len(reward)
    power = np.zeros_like(gap)
    power[1:] = power_after
    lead = rec["leader_speed_mps"][: steps + 1]
    lead_accel = np.zeros(steps + 1)
    lead_accel[1:] = np.diff(lead) / params.dt_s
    return Trajectory(
        gap_m=gap[: steps + 1], speed_mps=speed[: steps + 1], accel_mps2=accel[: steps + 1],
        power_kw=power[: steps + 1], leader_speed_mps=lead, leader_accel_mps2=lead_accel,
        reward=reward[:steps], tracking_reward=tracking[:steps],
        command_mps2=accel[1 : steps + 1].copy(), compute_s=np.zeros(steps),
        collided=bool(hit.size), steps=steps, bits_sent=0, solver_failures=0, dt_s=params.dt_s,
        automated=env.scenario.arrangement(env.n_vehicles).mask,  # every seat: the recorded cars
        settle_steps=settle_steps(env.scenario, params), ring=bool(env.scenario.ring),
    )

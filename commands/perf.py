"""``cacc-bench perf``: throughput of the environment, the harness, controllers and training.

Every figure is measured in this one run, side by side, so ratios are meaningful on a busy
machine; the published figures it compares with are constants from ``docs/spec/marl.md`` (measured on
this project's 2-core machine kind): the published environment runs about 4,000 steps/s with 8
followers (32,000 vehicle-steps/s); the published trainer about 307 (IA2C) and 195 (consensus)
environment steps/s.
"""

from __future__ import annotations

import dataclasses
import json
import time
from typing import Any

import numpy as np

from commands.cli import command_parser

PUBLISHED_ENV_VEHICLE_STEPS_PER_S = 32_000.0
PUBLISHED_TRAIN_STEPS_PER_S = {"ia2c": 307.0, "bdc": 195.0}
TARGET_ENV_VEHICLE_STEPS_PER_S = 10_000_000.0
#: Most seeds the population throughput trains at once.
MAX_PERF_POPULATION = 256


#: The mixed string ``perf`` times beside the homogeneous one: half the followers IDM humans
#: with their noise (issue: with humans, at least 80 % of the homogeneous env's speed).
MIXED_PERF_SCENARIO = "catchup-v1:cav_fraction=0.5"
#: The issue's target for ``env_mixed_ratio``.
MIXED_TARGET_RATIO = 0.8


def env_throughput(batch: int = 1024, n_vehicles: int = 8, seconds: float = 2.0,
                   scenario: str = "catchup-v1") -> dict[str, float]:
    """Batched env steps (physics, observations, reward with the power polynomial) per second.

    Commands come from the OVM law computed outside the timed region's env (they are part of
    the loop but not of the env); the env observes and computes the full reward (and, on a
    string with humans, drives the human seats).
    """
    from envs.dynamics import ovm_command_mps2
    from envs.platoon import PlatoonEnv

    env = PlatoonEnv(scenario, n_vehicles, observe=True)
    seeds = np.arange(batch)
    env.reset(seeds)
    s = env.state
    assert s is not None
    u = ovm_command_mps2(s.gap_m, s.speed_mps, s.pred_speed_mps, 0.5, 0.5)
    for _ in range(20):
        env.step(u)
    steps = 0
    env.reset(seeds)
    t0 = time.perf_counter()
    elapsed = 0.0
    while elapsed < seconds:
        for _ in range(50):
            if env.state is not None and env.state.step >= env.n_steps:
                env.reset(seeds)
            env.step(u)
        steps += 50
        elapsed = time.perf_counter() - t0
    rate = steps / elapsed
    return {
        "env_batch_steps_per_s": rate,
        "env_vehicle_steps_per_s": rate * batch * n_vehicles,
        "batch": float(batch),
        "n_vehicles": float(n_vehicles),
    }


def env_rates(rounds: int = 5, seconds: float = 1.0) -> dict[str, float]:
    """The homogeneous env (:func:`env_throughput`) and the env with humans
    (:data:`MIXED_PERF_SCENARIO`), timed in alternation (``rounds`` of each, ``seconds`` a time)
    so that a slow spell of the machine hits both: the homogeneous round of median rate, the
    median rate with humans, and their ratio (``env_mixed_ratio``; :data:`MIXED_TARGET_RATIO` is
    the target)."""
    import statistics

    homogeneous, mixed = [], []
    for _ in range(rounds):
        homogeneous.append(env_throughput(seconds=seconds))
        mixed.append(env_throughput(seconds=seconds, scenario=MIXED_PERF_SCENARIO)
                     ["env_vehicle_steps_per_s"])
    homogeneous.sort(key=lambda r: r["env_vehicle_steps_per_s"])
    h, m = homogeneous[len(homogeneous) // 2], statistics.median(mixed)
    return {**h, "env_mixed_vehicle_steps_per_s": m,
            "env_mixed_ratio": m / h["env_vehicle_steps_per_s"]}


#: The sweep ``harness_sweep_500_s`` times (the architecture issue's reference sweep).
SWEEP_CONTROLLERS = ("ovm", "acc", "cacc", "ia2c", "bdc")
SWEEP_SCENARIOS = ("catchup-v1", "slowdown-v1")


def harness_throughput(episodes: int = 10, sweep_episodes: int = 50) -> dict[str, float]:
    """The harness's closed loop without store or files, serial, batches as in ``run``:
    ``ovm`` on the default sweep (steps/s), and ``ovm, acc, cacc, ia2c, bdc`` on catchup-v1 and
    slowdown-v1 with ``sweep_episodes`` seeds each (``harness_sweep_<runs>_s``; 500 runs at 50)."""
    from benchmark.executors import run_keys
    from benchmark.suite import build_sweep, execute_run, seeds_from_episodes

    keys = build_sweep([("ovm", {})], ["catchup-v1", "slowdown-v1"], [8], seeds_from_episodes(episodes))
    execute_run(keys[0])  # warm caches (power polynomial, imports)
    t0 = time.perf_counter()
    steps = sum(int(r["steps"]) for r in run_keys(keys))
    wall = time.perf_counter() - t0
    sweep = build_sweep([(c, {}) for c in SWEEP_CONTROLLERS], list(SWEEP_SCENARIOS), [8],
                        seeds_from_episodes(sweep_episodes))
    for name in SWEEP_CONTROLLERS:  # warm: policy loading and imports
        execute_run(build_sweep([(name, {})], ["catchup-v1"], [8], [2000])[0])
    t0 = time.perf_counter()
    records = list(run_keys(sweep))
    sweep_s = time.perf_counter() - t0
    failed = [r["id"] for r in records if r["status"] != "ok"]
    if failed:
        raise RuntimeError(f"harness sweep: {len(failed)} run(s) failed, e.g. {failed[0]}")
    return {"harness_steps_per_s": steps / wall, "harness_default_sweep_s": wall,
            "harness_runs": float(len(keys)), f"harness_sweep_{len(sweep)}_s": sweep_s}


def shared_train_throughput(algo: str, steps: int = 131_072, n_vehicles: int = 8) -> float:
    """Environment steps per second of a shared-policy learner (:mod:`marl.ppo`, its default
    config, accel mode) on catchup-v1, learning without validation, one torch thread."""
    import torch

    from marl.ppo import PPOConfig, train

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        return float(train("catchup-v1", n_vehicles, 0, steps, PPOConfig(algo=algo))
                     .env_steps_per_s)
    finally:
        torch.set_num_threads(threads)


#: The scenario and the number of followers a controller is timed on.
TIMING_SCENARIO = "catchup-v1"
TIMING_VEHICLES = 8


def controller_timing(name: str, n_steps: int = 150, n_vehicles: int = TIMING_VEHICLES,
                      scenario_id: str = TIMING_SCENARIO,
                      options: dict[str, str] | None = None) -> dict[str, float]:
    """Wall time per vehicle per step of one controller, built with ``options`` (first call,
    the build, apart)."""
    from benchmark.rollout import rollout
    from controllers.registry import make_controller
    from envs.scenarios import make_scenario

    sc = make_scenario(scenario_id)
    sc = dataclasses.replace(sc, n_steps=min(n_steps, sc.n_steps))
    ctrl = make_controller(name, **(options or {}))
    traj = rollout(ctrl, sc, n_vehicles, 2000)
    ms = traj.compute_s * 1000.0 / n_vehicles
    rest = ms[1:]
    return {
        "median_ms": float(np.median(rest)),
        "p95_ms": float(np.percentile(rest, 95)),
        "p99_ms": float(np.percentile(rest, 99)),
        "first_ms": float(ms[0]),
        "steps": float(traj.steps),
    }


def sumo_throughput(quick: bool = False) -> dict[str, Any]:
    """The SUMO backend (``--only sumo``, the sumo extra): vehicle-steps per second of SUMO and
    of the built-in simulator on the same runs (:func:`studies.sumo_compare.speed_comparison`),
    and a small SUMO sweep through the process pool (two workers, each with its own libsumo),
    whose records must equal the serial ones."""
    from benchmark.executors import run_keys
    from benchmark.metrics import TIMING_COLUMNS
    from benchmark.suite import build_sweep
    from envs.simulators import check_simulator
    from studies.sumo_compare import speed_comparison

    check_simulator("sumo")
    table = speed_comparison(batch_sizes=(1, 4) if quick else (1, 10),
                             repeats=1 if quick else 2)
    out: dict[str, Any] = {"sumo_speed": table.to_dict(orient="records")}
    keys = build_sweep([("cacc", {}), ("plexe:ploeg", {})], ["catchup-v1"], [8],
                       [2000, 2010], simulator="sumo")
    serial = {r["id"]: r for r in run_keys(keys)}
    t0 = time.perf_counter()
    pooled = {r["id"]: r for r in run_keys(keys, "process", 2)}
    out["sumo_process_pool_s"] = time.perf_counter() - t0
    skip = {*TIMING_COLUMNS, "wall_s"}
    out["sumo_process_pool_equal"] = all(
        pooled[k][c] == v or (v != v and pooled[k][c] != pooled[k][c])  # NaN equals NaN
        for k, rec in serial.items() for c, v in rec.items() if c not in skip)
    if not out["sumo_process_pool_equal"]:
        raise RuntimeError("SUMO runs in the process pool differ from the serial ones")
    return out


def main(argv: list[str]) -> int:
    """Measure and print a table (``--json`` for a JSON object)."""
    from controllers.registry import available_controllers
    from infra.errors import ConfigError, ControllerContractError
    from marl.learners import PAPER_ALGORITHMS

    p = command_parser("perf", __doc__, raw=True)
    p.add_argument("--json", action="store_true", help="print one JSON object instead of a table")
    p.add_argument("--quick", action="store_true", help="shorter measurements (for tests)")
    p.add_argument("--only", default="env,harness,controllers,train",
                   help="comma list of parts: env, harness, controllers, train (default: all), "
                        "and sumo (the SUMO backend against the built-in simulator; the sumo "
                        "extra)")
    p.add_argument("--controllers", default=None,
                   help="comma list of controllers to time, with options as in run "
                        "(mpc:horizon=30,cacc); default: every available non-MARL controller "
                        "and every MARL policy with a shipped checkpoint")
    p.add_argument("--algos", default=None, help="comma list of MARL algorithms to time")
    p.add_argument("--population", type=int, default=6, metavar="K",
                   help="seeds trained at once for train_population_env_steps_per_s (default 6; "
                        "0: do not measure populations)")
    p.add_argument("--device", default="cpu",
                   help="where the training part trains: cpu (default) or cuda[:K]")
    args = p.parse_args(argv)
    parts = {x.strip() for x in args.only.split(",") if x.strip()}
    unknown = parts - {"env", "harness", "controllers", "train", "sumo"}
    if not parts:
        raise ConfigError("--only: no part named; valid: env, harness, controllers, train")
    if unknown:
        raise ConfigError(f"--only: unknown part(s) {sorted(unknown)}; valid: env, harness, controllers, train")
    specs: list[tuple[str, dict[str, str]]] = []
    if "controllers" in parts:  # bad names or options fail before anything is measured
        from controllers.registry import make_controller, parse_controller_list

        given = args.controllers is not None  # "" names nothing: refused, not the default
        specs = (parse_controller_list(args.controllers) if given
                 else [(c.name, {}) for c in available_controllers()])
        if not specs:
            raise ConfigError("--controllers: no controller named")
        if given:
            from benchmark.rollout import check_contract
            from envs.scenarios import make_scenario

            for name, opts in specs:
                ctrl = make_controller(name, **opts)  # checks the name and every option
                # a controller that breaks the loop's contract (a NaN command, an error in
                # act) is refused in one line before anything is measured
                check_contract(ctrl, make_scenario(TIMING_SCENARIO), TIMING_VEHICLES)
    from marl.learners import PPO_LEARNERS

    algos = ([a.strip() for a in args.algos.split(",") if a.strip()] if args.algos is not None
             else [*PAPER_ALGORITHMS, *PPO_LEARNERS])  # "" names nothing: refused below
    shared_algos = [a for a in algos if a in PPO_LEARNERS]
    algos = [a for a in algos if a not in PPO_LEARNERS]
    from infra.limits import check_range

    check_range(args.population, "--population", 0, MAX_PERF_POPULATION)
    unknown_algos = [a for a in algos if a not in PAPER_ALGORITHMS]
    if unknown_algos or not (algos or shared_algos):  # checked whichever parts run
        raise ConfigError(f"--algos: unknown algorithm(s) {unknown_algos or '(none named)'}; "
                          f"valid: {', '.join([*PAPER_ALGORITHMS, *PPO_LEARNERS])}")
    if "train" in parts:
        from marl.config import training_device

        training_device(args.device)  # ConfigError for an unknown device or a missing GPU
    out: dict[str, Any] = {}
    if "env" in parts:
        out.update(env_rates(rounds=3 if args.quick else 5, seconds=0.25 if args.quick else 1.0))
        out["env_speedup_vs_published"] = out["env_vehicle_steps_per_s"] / PUBLISHED_ENV_VEHICLE_STEPS_PER_S
    if "harness" in parts:
        out.update(harness_throughput(episodes=2 if args.quick else 10,
                                      sweep_episodes=2 if args.quick else 50))
    if "controllers" in parts:
        from controllers.registry import controller_label

        timing: dict[str, dict[str, float] | str] = {}
        for name, opts in specs:
            label = controller_label(name, opts)
            try:
                timing[label] = controller_timing(name, n_steps=40 if args.quick else 150,
                                                  options=opts)
            except Exception as exc:  # a missing checkpoint, say: report it, keep measuring
                if args.controllers and isinstance(exc, ControllerContractError):
                    raise ConfigError(f"{exc} while timed; fix the controller (its contract: "
                                      "controllers.base.Controller)") from None
                if args.controllers:
                    raise
                timing[label] = f"not measured: {exc}"
        out["controller_ms_per_vehicle_step"] = {
            k: v["median_ms"] for k, v in timing.items() if isinstance(v, dict)
        }
        out["controller_timing"] = timing
    if "train" in parts:
        try:
            from marl.perf import train_throughput
        except ImportError:
            train_throughput = None  # type: ignore[assignment]
        # repeats interleaved across algorithms (a slow spell of the machine hits them all), the
        # median reported: single 3e4-step runs of the same seed varied by up to 25 % here
        repeats = 1 if args.quick else 3
        runs: dict[str, list[float]] = {algo: [] for algo in algos}
        if train_throughput is not None:
            if algos:  # warm-up, not counted: the process's first training pays one-time costs
                train_throughput(algos[0], steps=500, device=args.device)
            for _ in range(repeats):
                for algo in algos:
                    rate = train_throughput(algo, steps=4_000 if args.quick else 20_000,
                                            device=args.device)
                    runs[algo].append(float(rate))
        for _ in range(repeats if shared_algos else 0):
            for algo in shared_algos:
                rate = shared_train_throughput(algo, steps=8_192 if args.quick else 131_072)
                out.setdefault("train_shared_env_steps_per_s_runs", {}).setdefault(
                    algo, []).append(rate)
        if shared_algos:
            out["train_shared_env_steps_per_s"] = {
                a: float(np.median(r)) for a, r in out["train_shared_env_steps_per_s_runs"].items()}
            from marl.perf import shared_network_bound

            # what the default config's networks alone allow: the learner cannot pass it here
            out["train_shared_network_bound_env_steps_per_s"] = float(
                shared_network_bound(repeats=2 if args.quick else 6))
        rates = {algo: float(np.median(r)) for algo, r in runs.items() if r}
        out["train_env_steps_per_s"] = rates
        out["train_device"] = args.device
        out["train_env_steps_per_s_runs"] = {algo: r for algo, r in runs.items() if r}
        if train_throughput is not None and args.population > 0 and algos:
            # the same per-run budget as the one-run figure, K seeds at once, one measurement
            # (K runs average the spread of one)
            out["train_population_size"] = args.population
            out["train_population_env_steps_per_s"] = {
                algo: float(train_throughput(algo, steps=4_000 if args.quick else 20_000,
                                             population=args.population, device=args.device))
                for algo in algos}
    if "sumo" in parts:
        out.update(sumo_throughput(quick=args.quick))
    if args.json:
        print(json.dumps(out, indent=2, sort_keys=True))
    else:
        _print_table(out)
    return 0


def _print_table(out: dict[str, Any]) -> None:
    for row in out.get("sumo_speed", []):
        print(f"SUMO backend, {row['controller']} on {row['scenario']} (B = {row['batch']}): "
              f"{row['vehicle_steps_per_s_sumo']:,.0f} vehicle-steps/s in SUMO, "
              f"{row['vehicle_steps_per_s_builtin']:,.0f} built-in ({row['ratio']:.1f}x)")
    if "sumo_process_pool_s" in out:
        print(f"SUMO sweep in the process pool (2 workers): {out['sumo_process_pool_s']:.2f} s, "
              f"records equal to the serial ones: {out['sumo_process_pool_equal']}")
    if "env_vehicle_steps_per_s" in out:
        print("environment (B = 1024, N = 8, observations + reward with power polynomial):")
        print(f"  {out['env_vehicle_steps_per_s'] / 1e6:10.2f} M vehicle-steps/s  "
              f"({out['env_speedup_vs_published']:.0f}x the published env's 32,000; "
              f"target >= {TARGET_ENV_VEHICLE_STEPS_PER_S / 1e6:.0f} M)")
    if "env_mixed_ratio" in out:
        print(f"  with humans ({MIXED_PERF_SCENARIO}), timed in alternation with the "
              f"homogeneous env: {out['env_mixed_vehicle_steps_per_s'] / 1e6:.2f} against "
              f"{out['env_vehicle_steps_per_s'] / 1e6:.2f} M vehicle-steps/s, "
              f"ratio {out['env_mixed_ratio']:.2f} (target >= {MIXED_TARGET_RATIO:.2f})")
    if "harness_steps_per_s" in out:
        print(f"harness (ovm, default sweep of {int(out['harness_runs'])} runs): "
              f"{out['harness_steps_per_s']:,.0f} steps/s, {out['harness_default_sweep_s']:.2f} s")
        for key in sorted(k for k in out if k.startswith("harness_sweep_")):
            runs = key.split("_")[2]
            print(f"harness sweep ({', '.join(SWEEP_CONTROLLERS)} on {' and '.join(SWEEP_SCENARIOS)}, "
                  f"{runs} runs, serial): {out[key]:.2f} s")
    if "controller_timing" in out:
        print("controllers (ms per vehicle per step; first call apart):")
        w = max([10, *(len(name) for name in out["controller_timing"])])
        print(f"  {'name':<{w}} {'median':>9} {'p95':>9} {'p99':>9} {'first':>9}")
        for name, t in out["controller_timing"].items():
            if isinstance(t, dict):
                print(f"  {name:<{w}} {t['median_ms']:9.4f} {t['p95_ms']:9.4f} "
                      f"{t['p99_ms']:9.4f} {t['first_ms']:9.2f}")
            else:
                print(f"  {name:<{w}} {t}")
    if "train_env_steps_per_s" in out:
        from marl.learners import PER_AGENT_SHARED

        print(f"training on {out['train_device']} (environment steps/s, one process, one torch "
              "thread; median of the runs):")
        if not out["train_env_steps_per_s"] and not out.get("train_shared_env_steps_per_s"):
            print("  (no MARL trainer available)")
        for algo, rate in out["train_env_steps_per_s"].items():
            ref = PUBLISHED_TRAIN_STEPS_PER_S.get(algo, PUBLISHED_TRAIN_STEPS_PER_S["ia2c"])
            runs = out.get("train_env_steps_per_s_runs", {}).get(algo, [rate])
            spread = f", runs {min(runs):,.0f} to {max(runs):,.0f}" if len(runs) > 1 else ""
            print(f"  {algo:<10} {rate:10,.0f}  ({rate / ref:.1f}x the published {ref:.0f}"
                  f"{spread})")
        for algo, rate in out.get("train_shared_env_steps_per_s", {}).items():
            runs = out["train_shared_env_steps_per_s_runs"][algo]
            spread = f", runs {min(runs):,.0f} to {max(runs):,.0f}" if len(runs) > 1 else ""
            kind = ("a network per follower, BDC's consensus" if algo in PER_AGENT_SHARED
                    else "one policy shared by the followers")
            print(f"  {algo:<10} {rate:10,.0f}  ({kind}, accel mode; target 34,000{spread})")
        if "train_shared_network_bound_env_steps_per_s" in out:
            print(f"  {'bound':<10} "
                  f"{out['train_shared_network_bound_env_steps_per_s']:10,.0f}  (the default "
                  "config's networks alone: no shared learner trains faster here)")
        if "train_population_env_steps_per_s" in out:
            k = out["train_population_size"]
            print(f"training a population of {k} seeds in one process, one torch thread (total "
                  "environment steps/s; one run's figure above):")
            for algo, rate in out["train_population_env_steps_per_s"].items():
                one = out["train_env_steps_per_s"].get(algo)
                ratio = f"  ({rate / one:.2f}x one run)" if one else ""
                print(f"  {algo:<10} {rate:10,.0f}{ratio}")

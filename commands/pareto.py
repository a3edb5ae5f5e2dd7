"""``cacc-bench pareto``: energy against spacing error for every controller family.

Each family is swept along its own energy/tracking knob (``mpc``: the energy weight;
``mpc-qp`` and ``cmpc``: the input weight against tracking; ``cacc``: time gap and gain);
BDC and IA2C along the power weight w5 of their training reward (shipped variants); ``ovm``,
``duty`` and the other MARL policies are single points, as is every controller ``--controllers``
adds (a registered one with its options, or ``package.module:Class`` of the user's). Runs go
through the results
store and the harness executors (resumable, identical on every executor); ``OUT/pareto.csv``
and one figure per scenario come out.
"""

from __future__ import annotations

import argparse
import sys
from typing import Any

from benchmark.export import write_csv
from commands.cli import add_scenarios_option, add_study_options, check_executor, command_parser
from infra.errors import ConfigError, UnknownNameError
from infra.files import read_csv

#: family -> (controller, knob, values). The defaults sit inside each sweep (mpc 0.25, w_accel
#: 0.1, time gap 0.5 s, kp 0.2).
SWEEPS: dict[str, tuple[str, str, tuple[float, ...]]] = {
    "mpc (energy weight)": ("mpc", "energy_weight", (0.0, 0.1, 0.25, 0.5, 1.0, 2.0)),
    "mpc-qp (input weight)": ("mpc-qp", "w_accel", (0.01, 0.03, 0.1, 0.3, 1.0, 3.0)),
    "cmpc (input weight)": ("cmpc", "w_accel", (0.01, 0.1, 1.0, 3.0)),
    "cacc (time gap)": ("cacc", "time_gap_s", (0.3, 0.5, 0.8, 1.2)),
    "cacc (gain kp)": ("cacc", "kp", (0.1, 0.2, 0.4)),
}

#: MARL algorithms swept along the power weight w5 of their training reward (-10 is the
#: shipped leaderboard policy; the others are shipped variants ``w5_<value>``, seed 0, made by
#: ``cacc-bench train --algo bdc,ia2c --scenario catchup-v1 --tuned --set reward_w_power=W``).
MARL_SWEEPS: dict[str, tuple[float, ...]] = {
    "bdc": (0.0, -1.0, -5.0, -10.0, -20.0),
    "ia2c": (0.0, -1.0, -5.0, -10.0, -20.0),
}
#: The power weight of the shipped leaderboard policies.
DEFAULT_W5 = -10.0


def w5_variant(w5: float) -> str:
    """Folder name of the shipped variant trained with power weight ``w5`` (``w5_m1`` for -1)."""
    return f"w5_{'m' if w5 < 0 else ''}{abs(w5):g}"


#: Controllers shown as single points.
POINTS: tuple[str, ...] = ("ovm", "duty")

#: Families by the name ``--families`` takes.
FAMILY_GROUPS: dict[str, tuple[str, ...]] = {
    "mpc": ("mpc (energy weight)",),
    "mpc-qp": ("mpc-qp (input weight)",),
    "cmpc": ("cmpc (input weight)",),
    "cacc": ("cacc (time gap)", "cacc (gain kp)"),
    "points": (),
    "marl": (),
}


def _parser() -> argparse.ArgumentParser:
    p = command_parser("pareto", __doc__)
    add_scenarios_option(p, "catchup-v1")
    p.add_argument("--episodes", type=int, default=3,
                   help="first K published evaluation seeds per setting (default: %(default)s)")
    p.add_argument("--vehicles", type=int, default=8, help="followers N (default: 8)")
    p.add_argument("--families", default=",".join(FAMILY_GROUPS),
                   help="comma list among " + ", ".join(FAMILY_GROUPS) + " (default: all)")
    p.add_argument("--controllers", default=None,
                   help="more controllers, each a single point beside the families (comma list "
                        "with options as name:key=value, or my_module:MyController; default: "
                        "none)")
    p.add_argument("--energy", choices=("total", "controllable"), default="total",
                   help="energy objective: the total energy per vehicle, or only its part above "
                        "steady cruise at the leader's mean speed (docs/controllable-energy.md); "
                        "controllable writes pareto-controllable.csv and its own figures beside "
                        "pareto.csv (default: %(default)s)")
    add_study_options(p, "results/pareto", "sweep")
    return p


def settings_for(families: list[str], scenarios: list[str], n_vehicles: int
                 ) -> list[dict[str, Any]]:
    """The controller settings of the chosen families: label, family, controller, knob, value,
    options."""
    from controllers.policy import VARIANT_DIR, checkpoint_path
    from controllers.registry import controller_label
    from marl.learners import PAPER_ALGORITHMS

    out: list[dict[str, Any]] = []

    def add(family: str, name: str, opts: dict[str, str], knob: str, value: Any) -> None:
        out.append({"label": controller_label(name, opts), "family": family, "controller": name,
                    "knob": knob, "knob_value": value, "options": opts})

    for group in families:
        for family in FAMILY_GROUPS[group]:
            name, knob, values = SWEEPS[family]
            for v in values:
                add(family, name, {knob: f"{v:g}"}, knob, v)
        if group == "points":
            for name in POINTS:
                add(name, name, {}, "", "")
        if group == "marl":
            from controllers.policy import IPPO_VARIANTS
            from marl.learners import SHARED_LEARNERS

            for algo in (*PAPER_ALGORITHMS, *SHARED_LEARNERS):
                if not all(checkpoint_path(algo, sc, n_vehicles).exists() for sc in scenarios):
                    continue
                if algo not in MARL_SWEEPS:
                    add(f"marl {algo}", algo, {}, "", "")
                    if algo == "ippo":  # its shipped variants, as points beside it
                        for variant in IPPO_VARIANTS:
                            if all(checkpoint_path(algo, sc, n_vehicles, 0, VARIANT_DIR / variant)
                                   .exists() for sc in scenarios):
                                add(f"marl ippo {variant}", algo, {"variant": variant}, "", "")
                    continue
                for w5 in MARL_SWEEPS[algo]:
                    opts = {} if w5 == DEFAULT_W5 else {"variant": w5_variant(w5)}
                    folder = VARIANT_DIR / opts["variant"] if opts else None
                    if all(checkpoint_path(algo, sc, n_vehicles, 0, folder).exists()
                           for sc in scenarios):
                        add(f"marl {algo} (power weight w5)", algo, opts, "reward_w_power", w5)
    return out


def main(argv: list[str]) -> int:
    """Entry point of ``cacc-bench pareto``."""
    from analysis.pareto import ENERGY_METRICS, pareto_frame, plot_pareto
    from benchmark.suite import build_sweep, seeds_from_episodes
    from commands.cli import scenarios_argument
    from commands.run import study_sweep
    from envs.scenarios import check_vehicles

    args = _parser().parse_args(argv)

    scenarios = scenarios_argument(args.scenarios)
    labels = [sc.label for sc in scenarios]
    families = list(dict.fromkeys(f.strip() for f in args.families.split(",") if f.strip()))
    if not families:
        raise ConfigError("--families: nothing named")
    for f in families:
        if f not in FAMILY_GROUPS:
            raise UnknownNameError("family", f, FAMILY_GROUPS)
    if args.episodes < 1:
        raise ConfigError(f"--episodes must be >= 1, got {args.episodes}")
    check_vehicles(args.vehicles)
    check_executor(args.workers, args.ray_address)
    settings = settings_for(families, labels, args.vehicles)
    if args.controllers is not None:
        from controllers.registry import controller_label, parse_controller_list

        held = {s["label"] for s in settings}
        for name, opts in parse_controller_list(args.controllers):
            label = controller_label(name, opts)
            if label not in held:
                held.add(label)
                settings.append({"label": label, "family": label, "controller": name,
                                 "knob": "", "knob_value": "", "options": opts})
    if not settings:
        raise ConfigError("nothing to run: no shipped MARL policy for these scenarios and N")
    seeds = seeds_from_episodes(args.episodes)
    keys = build_sweep([(s["controller"], s["options"]) for s in settings], scenarios,
                       [args.vehicles], seeds)
    controllers = len({s["label"] for s in settings})
    shared = (f" ({len(settings)} sweep points: a default lies in two sweeps)"
              if len(settings) > controllers else "")
    with study_sweep(keys, args, f"pareto: {controllers} controllers{shared} x "
                     f"{len(scenarios)} scenarios x {len(seeds)} episodes = {len(keys)} runs",
                     seeds[0]) as (out, rc):
        runs = read_csv(out / "runs" / "runs.csv", "the runs table",
                        columns=("status", "n_vehicles"))
        runs = runs[(runs["status"] == "ok") & (runs["n_vehicles"] == args.vehicles)]
        energy_col = ENERGY_METRICS[args.energy]
        unknown = int(runs[energy_col].isna().sum()) if energy_col in runs else len(runs)
        if args.energy != "total" and unknown:
            print(f"pareto: {unknown} of {len(runs)} runs in {out / 'runs'} were stored before "
                  "controllable energy was measured (no value); their settings have no point: "
                  "run the sweep into a new --out", file=sys.stderr)
        df = pareto_frame(runs, settings, args.energy)
        suffix = "" if args.energy == "total" else f"-{args.energy}"
        csv_path = out / f"pareto{suffix}.csv"
        write_csv(df, csv_path)
        for sc in labels:
            plot_pareto(df, sc, out / "figures", f"pareto{suffix}__{sc}__n{args.vehicles}",
                        args.energy)
    front = df[df["non_dominated"]]
    print(f"wrote {csv_path} ({len(df)} points, {len(front)} non-dominated) and "
          f"{out / 'figures'}")
    what = "kWh/100 km" if args.energy == "total" else "kWh/100 km above cruise"
    for _, r in front.iterrows():
        print(f"  {r['scenario']}: {r['controller']} {r[f'{energy_col}_mean']:.2f} "
              f"{what}, gap RMSE {r['gap_rmse_m_mean']:.2f} m")
    return rc

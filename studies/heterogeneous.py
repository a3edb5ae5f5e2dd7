"""The heterogeneous study: strings of a bus, a van and cars in three orders, with and without
human drivers, under every controller family (issue 55 item 6).

The design (:func:`design`) crosses the orders of :data:`ORDERS` (heavy first, heavy last,
spread) with and without the human seats of :data:`HUMANS` on the scenarios of
:data:`SCENARIOS`; every family of :data:`DEFAULT_FAMILIES` drives the automated seats, and the
all-human string of each order (the IDM in every seat, ``cavs=0``) is the baseline row.
:func:`cells` gives one row per scenario, order, human setting and family: runs, collisions,
the smallest gap, the gap error, the head-to-tail gain and the energy per class and of the string
(``docs/vehicle-classes.md``). :func:`head_to_tail_peaks` sets the analytic head-to-tail gain of
:mod:`analysis.head_to_tail` beside the measured one on the ``sine-v1`` sweep, per order and
linear family; :func:`plot_peaks` and :func:`plot_energy` draw them; :func:`write_report`
writes ``README.md``.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from analysis.plots import save_png
from analysis.tables import num, table_lines
from studies.penetration import BASELINE, families_of

if TYPE_CHECKING:
    from envs.scenarios import Scenario

#: The orders of the study: eight followers, one bus, one van and six cars.
ORDERS: dict[str, str] = {
    "heavy first": "bus+van+car*6",
    "heavy last": "car*6+van+bus",
    "spread": "car*2+bus+car*2+van+car*2",
}
#: The human seats of the mixed variant (followers 2 and 7: a human-driven van in the heavy-first
#: and heavy-last orders, two human cars in the spread one).
HUMANS = "2+7"
#: The families the study runs by default, in the report's order: the linear laws (the xiao
#: rule gives each vehicle the time gap its own lag needs), the MPC and a shared learned policy
#: (ippo trained on mixed traffic; it senses no class).
DEFAULT_FAMILIES: tuple[str, ...] = ("acc", "cacc", "cacc:time_gap_rule=xiao", "mpc-qp",
                                     "ippo:scenario=mixed-v2,variant=mixed-traffic")
#: The scenarios of the study.
SCENARIOS: tuple[str, ...] = ("catchup-v1", "slowdown-v1", "brake-v1")
#: The families with an analytic head-to-tail model (:data:`analysis.head_to_tail.ANALYTIC_CONTROLLERS`),
#: as (label, controller, options).
ANALYTIC_FAMILIES: tuple[tuple[str, str, dict[str, str]], ...] = (
    ("acc", "acc", {}), ("cacc", "cacc", {}),
    ("cacc[time_gap_rule=xiao]", "cacc", {"time_gap_rule": "xiao"}))
#: The frequencies (rad/s) of the head-to-tail peak: up to 1 rad/s, where analysis and
#: measurement agree within 2 % (``tests/test_analysis/test_head_to_tail.py``).
PEAK_OMEGAS_RAD_S: tuple[float, ...] = (0.1, 0.2, 0.3, 0.4, 0.5, 0.7, 1.0)
#: The columns a cell reports (mean over its episodes), with the report's names.
METRICS: tuple[tuple[str, str], ...] = (
    ("gap_rmse_m", "gap RMSE m"),
    ("head_to_tail_gain", "head-to-tail gain"),
    ("energy_kwh_per_100km", "string kWh/100 km"),
    ("energy_kwh_per_100km_bus", "bus kWh/100 km"),
    ("energy_kwh_per_100km_van", "van kWh/100 km"),
    ("energy_kwh_per_100km_car", "car kWh/100 km"),
)


@dataclass(frozen=True)
class Setting:
    """One setting of the design: a scenario with an order, with or without humans.

    Attributes
    ----------
    scenario : str
        The scenario's label.
    order : str
        A key of :data:`ORDERS`.
    humans : str
        ``"none"`` (every seat automated), ``"mixed"`` (the seats of :data:`HUMANS`) or
        ``"all"`` (the all-human baseline).
    """

    scenario: str
    order: str
    humans: str

    def build(self) -> Scenario:
        """The scenario with this order and these human seats."""
        from envs.scenarios import make_scenario

        opts = {"classes": ORDERS[self.order]}
        if self.humans == "mixed":
            opts["humans"] = HUMANS
        elif self.humans == "all":
            opts["cavs"] = "0"
        return make_scenario(self.scenario, **opts)


def design(scenarios: Sequence[str] = SCENARIOS) -> list[Setting]:
    """Every order of every scenario without humans, with the human seats, and all-human."""
    return [Setting(sc, order, h) for sc in scenarios for order in ORDERS
            for h in ("none", "mixed", "all")]


def controllers_for(setting: Setting, families: Sequence[tuple[str, dict[str, str]]]
                    ) -> list[tuple[str, dict[str, str]]]:
    """The controllers that run a setting: the human baseline on the all-human string, the
    families elsewhere."""
    return [(BASELINE, {})] if setting.humans == "all" else list(families)


def cells(runs: Any, settings: Sequence[Setting]) -> Any:
    """One row per (scenario, order, humans, controller): runs, colliding runs, the smallest
    gap over its runs and the mean over its runs of every metric of :data:`METRICS` (NaN: not
    defined, as the head-to-tail gain behind ``catchup-v1``'s constant-speed leader).

    Parameters
    ----------
    runs : pandas.DataFrame
        ``runs.csv`` of the study's sweep.
    settings : sequence of Setting
        The design; a run's scenario label maps back to its setting.
    """
    import pandas as pd

    rows = []
    for s in settings:
        of_setting = runs[runs["scenario"] == s.build().label]
        for controller, g in of_setting.groupby("controller", sort=False):
            row: dict[str, Any] = {
                "scenario": s.scenario, "order": s.order, "humans": s.humans,
                "classes": ORDERS[s.order], "controller": controller, "runs": len(g),
                "failed": int((g["status"] != "ok").sum()),
                "collisions": int(g["collision"].astype(bool).sum()),
                "min_gap_m": float(pd.to_numeric(g["min_gap_m"], errors="coerce").min())}
            for col, _ in METRICS:
                values = pd.to_numeric(g[col], errors="coerce").to_numpy(dtype=np.float64)
                row[col] = float(np.mean(values)) if np.isfinite(values).all() else math.nan
            rows.append(row)
    return pd.DataFrame(rows)


def head_to_tail_peaks(orders: Sequence[str] = tuple(ORDERS), n_vehicles: int = 8) -> Any:
    """The head-to-tail peak gain ``max_w |A_N / A_0|`` over :data:`PEAK_OMEGAS_RAD_S`, analytic
    (:func:`analysis.head_to_tail.head_to_tail_gain`) and measured (the ``sine-v1`` sweep), for
    every family of :data:`ANALYTIC_FAMILIES` on every order with and without humans, for the
    all-IDM string of every order, and for the homogeneous string (``"i3 x 8"``, no classes) as
    the reference. One row per (order, humans, family): both peaks, the frequency of the
    analytic one and the largest relative difference over the frequencies."""
    import pandas as pd

    from analysis.head_to_tail import compare

    w = np.asarray(PEAK_OMEGAS_RAD_S)
    cases: list[tuple[str, str, str, str, dict[str, str], dict[str, str]]] = []
    for label, ctrl, opts in ANALYTIC_FAMILIES:
        cases.append(("homogeneous", "none", label, ctrl, opts, {}))
        for order in orders:
            cases.append((order, "none", label, ctrl, opts, {"classes": ORDERS[order]}))
            cases.append((order, "mixed", label, ctrl, opts,
                          {"classes": ORDERS[order], "humans": HUMANS}))
    for order in orders:
        cases.append((order, "all", BASELINE, "idm", {}, {"classes": ORDERS[order], "cavs": "0"}))
    rows = []
    for order, humans, label, ctrl, opts, arrangement in cases:
        r = compare(ctrl, arrangement, w, n_vehicles, opts)
        i = int(np.argmax(r.analytic))
        rows.append({"order": order, "humans": humans, "controller": label,
                     "classes": arrangement.get("classes", "i3*8 (homogeneous)"),
                     "peak_analytic": float(r.analytic.max()),
                     "peak_measured": float(r.measured.max()),
                     "omega_at_peak_rad_s": float(w[i]),
                     "max_relative_difference": r.max_relative_error})
    return pd.DataFrame(rows)


def _bars(ax: Any, t: Any, families: Sequence[str], orders: Sequence[str], column: str,
          label: str, mark: Callable[[Any, np.ndarray, Any, Any], Any], **style: Any) -> None:
    """``column`` of each family of ``t`` as bars over ``orders`` (the x axis), the families
    side by side; ``mark(ax, x, rows, bars)`` adds a family's markers."""
    width = 0.8 / max(len(families), 1)
    for k, fam in enumerate(families):
        f = t[t["controller"] == fam].set_index("order").reindex(orders)
        x = np.arange(len(orders)) + (k - (len(families) - 1) / 2) * width
        mark(ax, x, f, ax.bar(x, f[column], width, label=label.format(fam), **style))
    ax.set_xticks(np.arange(len(orders)))
    ax.set_xticklabels(orders, fontsize=8)
    ax.grid(alpha=0.3, axis="y")


def plot_peaks(peaks: Any, path: Path) -> Path:
    """The head-to-tail peak gain against the arrangement, analytic (bars) and measured
    (crosses), one panel per human setting, one colour per family (log scale; the line at 1:
    the string damps from head to tail below it)."""
    from analysis.plots import _plt

    def measured(ax: Any, x: np.ndarray, f: Any, bars: Any) -> None:
        ax.plot(x, f["peak_measured"], "x", color=bars.patches[0].get_facecolor(), ms=8, mew=2,
                alpha=1.0)

    panels = [("none", "every seat automated"), ("mixed", f"humans at seats {HUMANS}")]
    fig, axes = _plt().subplots(1, 2, figsize=(10, 3.8), sharey=True)
    for ax, (humans, title) in zip(axes, panels, strict=True):
        t = peaks[peaks["humans"] == humans]
        _bars(ax, t, families_of(peaks), list(dict.fromkeys(t["order"])), "peak_analytic",
              "{} (analytic)", measured, alpha=0.6)
        ax.axhline(1.0, color="grey", lw=0.8, ls="--")
        ax.set_yscale("log")
        ax.set_title(title, fontsize=9)
    axes[0].set_ylabel("head-to-tail peak gain (0.1-1 rad/s)")
    axes[1].plot([], [], "kx", label="measured (sine-v1 sweep)")
    axes[1].legend(fontsize=7, loc="best")
    return save_png(fig, path)


def plot_energy(table: Any, path: Path) -> Path:
    """The string's energy (kWh/100 km) per order and family, one panel per scenario, runs of
    every seat automated (a cross: a cell with a collision, whose runs ended early)."""
    from analysis.plots import _plt

    def collided(ax: Any, x: np.ndarray, f: Any, _: Any) -> None:
        hit = f["collisions"].fillna(0).to_numpy() > 0
        ax.plot(x[hit], f["energy_kwh_per_100km"].to_numpy()[hit], "kx", ms=7)

    scenarios = list(dict.fromkeys(table["scenario"]))
    fig, axes = _plt().subplots(1, len(scenarios), figsize=(4.2 * len(scenarios), 3.6),
                                squeeze=False)
    t_all = table[table["humans"] == "none"]
    for ax, sc in zip(axes[0], scenarios, strict=True):
        _bars(ax, t_all[t_all["scenario"] == sc], list(dict.fromkeys(t_all["controller"])),
              list(ORDERS), "energy_kwh_per_100km", "{}", collided)
        ax.set_title(sc, fontsize=9)
    axes[0][0].set_ylabel("string energy kWh/100 km")
    axes[0][-1].legend(fontsize=6, loc="best")
    return save_png(fig, path)


def findings(table: Any, peaks: Any) -> list[str]:
    """The report's reading, computed from the cells and the peaks: collisions per family and
    human setting over the orders and scenarios; the order with the largest analytic peak per
    family; the largest relative difference between analysis and measurement."""
    def collided(t: Any) -> str:
        return f"{int(t['collisions'].sum())}/{int(t['runs'].sum())}"

    analytic = peaks[peaks["humans"] == "none"]
    by_order = []
    for fam in families_of(peaks):
        t = analytic[analytic["controller"] == fam].set_index("order")
        by_order.append([f"`{fam}`", *(num(t.loc[o, "peak_analytic"] if o in t.index else math.nan,
                                           ".3g") for o in ("homogeneous", *ORDERS))])
    worst = float(peaks["max_relative_difference"].max())
    return [
        "## Reading", "",
        "Colliding runs of each family over the three orders and the three scenarios "
        "(runs with a collision / runs):", "",
        *table_lines(["family", "every seat automated", "humans at seats " + HUMANS],
                     ([f"`{fam}`", *(collided(table[(table["controller"] == fam)
                                                    & (table["humans"] == humans)])
                                     for humans in ("none", "mixed"))]
                      for fam in families_of(table))),
        f"| `{BASELINE}` (every seat human) | {collided(table[table['controller'] == BASELINE])}"
        " | |", "",
        "Head-to-tail peak gain (analytic, 0.1-1 rad/s) of each linear family, every seat "
        "automated, by order (the homogeneous string for reference):", "",
        *table_lines(["family", "homogeneous", *ORDERS], by_order),
        "", f"Analysis and measurement of the head-to-tail gain differ by at most "
        f"{100 * worst:.2g} % over every case and frequency of the figure.", ""]


def write_report(table: Any, peaks: Any, out: Path, command: str, episodes: int,
                 figures: Sequence[Path]) -> Path:
    """``README.md``: the command, the design, the reading, the figures and one table per
    scenario (paths relative to ``out``)."""
    from infra.atomic import write_text

    lines = [
        "# Heterogeneous platoons: a bus, a van and six cars in three orders",
        "",
        f"Made by `{command}`. {episodes} test episode(s) per cell (the first of the test seed "
        "set, `--episodes`): a small study for a two-core machine, so a cell's numbers are "
        "those of so many runs (their mean), without intervals. Eight followers: one bus, one "
        "van and "
        "six cars (`docs/vehicle-classes.md`) in the orders "
        + ", ".join(f"{k} (`classes={v}`)" for k, v in ORDERS.items())
        + f"; every seat automated, or humans (IDM with noise) at seats {HUMANS}, or every seat "
        "human (the `idm` baseline). The energy per class is each class's battery energy over "
        "its own distance; the string's is every follower's over every follower's (per "
        "vehicle). No platoon drag saving (`drag_saving=none`). A colliding run ends at its "
        "collision, often while braking hard: read its energy (negative where regeneration "
        "ended it) and gains with the collision count.",
        "",
        *findings(table, peaks),
    ]
    for fig in figures:
        lines += [f"![{fig.stem}]({fig.relative_to(out).as_posix()})", ""]
    lines += ["## Head-to-tail peaks", "",
              *table_lines(["order", "humans", "family", "analytic", "measured", "at rad/s",
                            "max rel. diff."],
                           ([r["order"], r["humans"], f"`{r['controller']}`",
                             num(r["peak_analytic"], ".4g"), num(r["peak_measured"], ".4g"),
                             f"{r['omega_at_peak_rad_s']:g}",
                             num(r["max_relative_difference"], ".2g")]
                            for _, r in peaks.iterrows())), ""]
    for scenario, t in table.groupby("scenario", sort=False):
        lines += [f"## {scenario}", "",
                  *table_lines(["order", "humans", "controller", "runs", "collisions",
                                "min gap m", *(name for _, name in METRICS)],
                               ([r["order"], r["humans"], f"`{r['controller']}`", r["runs"],
                                 r["collisions"], num(r["min_gap_m"], ".3g"),
                                 *(num(r[c], ".3g") for c, _ in METRICS)]
                                for _, r in t.iterrows())), ""]
    return write_text(out / "README.md", "\n".join(lines) + "\n")

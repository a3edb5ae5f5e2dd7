"""The penetration study: which controller family damps waves at what share of automated vehicles.

The design (:func:`design`) crosses the shares of :data:`SHARES` (no automated vehicle, one, a
quarter, half, three quarters, all) with every family of :data:`DEFAULT_FAMILIES` on the scenarios of
:data:`SCENARIOS`, with several seeded random placements of the automated vehicles for the
mixed shares; the all-human string (the human model ``idm`` at no automated vehicle) is the
baseline row of each scenario. :func:`cells` pools a share's placements and episodes into one
cell with 95 % bootstrap intervals (:func:`benchmark.statistics.bootstrap_ci`); :func:`plot_shares`
draws the head-to-tail gain and the energy against the share, per family; :func:`write_report`
writes ``report.md``. Metrics: ``docs/concepts/metrics.md`` (mixed traffic).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from analysis.plots import save_png
from analysis.tables import row, table_lines
from benchmark.statistics import bootstrap_ci

if TYPE_CHECKING:
    from envs.scenarios import Scenario

#: The learned family the study runs by default: ``ippo`` trained on mixed traffic (``mixed-v2``
#: and ``ring-v1``, automated shares 0.05 to 1 at random placements; the shipped variant
#: ``mixed-traffic``, docs/learned-control.md), its three training seeds one family
#: (:func:`family`).
LEARNED: tuple[str, ...] = tuple(f"ippo[scenario=mixed-v2,seed={k},variant=mixed-traffic]"
                                 for k in range(3))
#: The families the study runs by default (the automated seats' controller), in the report's
#: order; a table holds the controllers the command was given.
DEFAULT_FAMILIES: tuple[str, ...] = ("acc", "cacc", "mpc-qp", "mpc", "followerstopper",
                                     "pi-saturation", *LEARNED)
#: The human-driver model that drives every seat of the all-human baseline.
BASELINE: str = "idm"
#: The scenarios of the study (each at its own default N: 8 behind a leader, 4 on the OpenACC
#: window, 22 on the ring).
SCENARIOS: tuple[str, ...] = ("catchup-v1", "slowdown-v1", "brake-v1", "ring-v1", "openacc-s-v1")


@dataclass(frozen=True)
class Share:
    """One level of the share of automated vehicles.

    Attributes
    ----------
    name : str
        As the report prints it.
    options : dict
        The scenario options that set it.
    mixed : bool
        Humans and automated vehicles both present (the placement is drawn, several times).
    """

    name: str
    options: tuple[tuple[str, str], ...]
    mixed: bool


SHARES: tuple[Share, ...] = (
    Share("0", (("cavs", "0"),), False),
    Share("one vehicle", (("cavs", "1"),), True),
    Share("0.25", (("cav_fraction", "0.25"),), True),
    Share("0.5", (("cav_fraction", "0.5"),), True),
    Share("0.75", (("cav_fraction", "0.75"),), True),
    Share("1", (("cav_fraction", "1.0"),), False),
)

#: The columns a cell reports, with the report's names (mean and 95 % interval over episodes).
METRICS: tuple[tuple[str, str], ...] = (
    ("head_to_tail_gain", "head-to-tail gain"),
    ("speed_std_last_mps", "last vehicle speed std m/s"),
    ("speed_std_humans_mps", "humans' speed std m/s"),
    ("braking_events_per_veh_h", "braking events /veh/h"),
    ("speed_mean_mps", "mean speed m/s"),
    ("energy_kwh_per_100km", "energy kWh/100 km"),
    ("energy_humans_kwh", "humans' energy kWh"),
    ("energy_cavs_kwh", "automated energy kWh"),
)


@dataclass(frozen=True)
class Setting:
    """One setting of the design: a scenario (its label) at one share and placement."""

    scenario: str
    share: Share
    placement_seed: int

    def build(self) -> Scenario:
        """The scenario at this share and placement (``scenario`` is a label that may carry
        options of its own: ``ring-v1[length_m=230.0]``)."""
        from envs.scenarios import make_scenario

        opts = dict(self.share.options)
        if self.share.mixed:
            opts.update(placement="random", placement_seed=str(self.placement_seed))
        return make_scenario(self.scenario, **opts)


def design(scenarios: Sequence[str] = SCENARIOS, placements: int = 3) -> list[Setting]:
    """The scenario settings of the study: every share of every scenario, the mixed shares at
    ``placements`` seeded placements (``placement_seed`` 0, 1, ...)."""
    out = []
    for sc in scenarios:
        for share in SHARES:
            for k in range(placements if share.mixed else 1):
                out.append(Setting(sc, share, k))
    return out


def controllers_for(share: Share, families: Sequence[tuple[str, dict[str, str]]]
                    ) -> list[tuple[str, dict[str, str]]]:
    """The controllers (names with their options) that run at ``share``: the human baseline at
    no automated vehicle, the families elsewhere."""
    return [(BASELINE, {})] if share.name == "0" else list(families)


def family(label: str) -> str:
    """A controller's family in the study: its label without a training ``seed`` (the runs of
    a learned policy's training seeds pool into one family, as its placements and episodes)."""
    from infra.naming import format_label, parse_label

    name, options = parse_label(label)
    options.pop("seed", None)
    return format_label(name, options)


def cells(runs: Any, settings: Sequence[Setting]) -> Any:
    """One row per (scenario, family, share): runs, colliding runs, and every metric of
    :data:`METRICS` as mean and 95 % bootstrap interval over the episodes of all placements
    (and of all training seeds of a learned family, :func:`family`).

    Parameters
    ----------
    runs : pandas.DataFrame
        ``runs.csv`` of the study's sweep (columns ``controller``, ``scenario``, the metrics).
    settings : sequence of Setting
        The design; a run's scenario label maps back to its setting.
    """
    import pandas as pd

    label_of = {s.build().label: s for s in settings}
    rows = []
    ok = runs[runs["scenario"].isin(label_of)].copy()
    ok["base"] = [label_of[lb].scenario for lb in ok["scenario"]]
    ok["share"] = [label_of[lb].share.name for lb in ok["scenario"]]
    ok["controller"] = [family(c) for c in ok["controller"]]
    for (base, controller, share), g in ok.groupby(["base", "controller", "share"], sort=False):
        row: dict[str, Any] = {"scenario": base, "controller": controller, "share": share,
                               "cav_share": float(g["cav_share"].mean()),
                               "runs": len(g), "collisions": int(g["collision"].astype(bool).sum()),
                               "placements": int(g["scenario"].nunique())}
        for col, _ in METRICS:
            values = pd.to_numeric(g[col], errors="coerce").to_numpy(dtype=np.float64)
            mean, lo, hi = bootstrap_ci(values)
            row[col], row[f"{col}_lo"], row[f"{col}_hi"] = mean, lo, hi
        rows.append(row)
    order = {s.name: i for i, s in enumerate(SHARES)}
    fam = {family(f): i for i, f in enumerate((BASELINE, *DEFAULT_FAMILIES))}
    sc_order = {s: i for i, s in enumerate(dict.fromkeys(s.scenario for s in settings))}
    out = pd.DataFrame(rows)
    if out.empty:
        return out
    out = out.sort_values(by=["scenario", "controller", "share"],
                          key=lambda c: c.map({**sc_order, **fam, **order}).fillna(99))
    return out.reset_index(drop=True)


def families_of(table: Any) -> list[str]:
    """The controllers of a cells table other than the all-human baseline, in its order."""
    return [c for c in dict.fromkeys(table["controller"]) if c != BASELINE]


def _fmt(mean: float, lo: float, hi: float) -> str:
    if not math.isfinite(mean):
        return "n/a"
    return f"{mean:.3g} [{lo:.3g}, {hi:.3g}]"


def plot_shares(table: Any, out_dir: Path) -> list[Path]:
    """Per scenario, the head-to-tail gain (log scale) and the energy per vehicle against the
    share of automated vehicles, one line per family (the all-human baseline at share 0 a marker
    every line starts from; a cross marks a cell with collisions);
    ``figures/penetration-<scenario>.png``."""
    from analysis.plots import _plt

    paths = []
    for scenario, t in table.groupby("scenario", sort=False):
        fig, axes = _plt().subplots(1, 2, figsize=(9.5, 3.6))
        base = t[t["controller"] == BASELINE]
        for ax, col, ylabel in ((axes[0], "head_to_tail_gain", "head-to-tail gain"),
                                (axes[1], "energy_kwh_per_100km", "energy kWh/100 km (all)")):
            for family in families_of(t):
                f = t[t["controller"] == family]
                if f.empty:
                    continue
                f = f.sort_values("cav_share")
                x = np.concatenate([base["cav_share"].to_numpy(), f["cav_share"].to_numpy()])
                y = np.concatenate([base[col].to_numpy(), f[col].to_numpy()])
                (line,) = ax.plot(x, y, marker="o", ms=3, label=family)
                hit = f[f["collisions"] > 0]  # colliding cells: their runs ended early
                ax.plot(hit["cav_share"], hit[col], "x", ms=8, color=line.get_color())
            if not base.empty:
                ax.plot(base["cav_share"], base[col], "ks", label="all human (idm)")
            ax.set_xlabel("share of automated vehicles")
            ax.set_ylabel(ylabel)
            ax.grid(alpha=0.3)
        axes[0].axhline(1.0, color="grey", lw=0.8, ls="--")
        axes[0].set_yscale("log")
        axes[1].plot([], [], "kx", label="with collisions")
        axes[1].legend(fontsize=7, loc="best")
        fig.suptitle(str(scenario))
        paths.append(save_png(fig, out_dir / f"penetration-{scenario}.png"))
    return paths


#: Published numbers the report sets its ring results beside (sources in the report).
STERN_2018 = ("Stern et al. (2018), one automated car among 20 or more human drivers on a "
              "circular track (field experiment; Transportation Research Part C 89:205-221): the "
              "waves were dampened, with up to 40 % better fuel economy and over 90 % fewer "
              "braking events")
FLOW_2018 = ("Flow (Wu et al., arXiv 1710.05465; Kreidieh et al. 2018): learned control of "
             "4-7 % automated vehicles raised the system speed by up to 57 % in simulation")
CIRCLES_2024 = ("CIRCLES (arXiv 2401.09666): over 15 % fuel saving at 4 % penetration on I-24 "
                "trajectories (simulation)")


def _cell(table: Any, scenario: str, controller: str, share: str) -> Any:
    m = table[(table["scenario"] == scenario) & (table["controller"] == controller)
              & (table["share"].astype(str) == share)]
    return None if m.empty else m.iloc[0]


def _change(new: float, old: float) -> str:
    if not (math.isfinite(new) and math.isfinite(old)) or old == 0:
        return "n/a"
    return f"{100.0 * (new - old) / old:+.0f} %"


def findings(table: Any) -> list[str]:
    """The report's reading, computed from the cells: on the ring, one vehicle of each family
    against the all-human string, beside the published numbers; per scenario and share, the
    family with the smallest humans' speed spread among those without a collision."""
    lines = ["## Reading", ""]
    base = _cell(table, "ring-v1", BASELINE, "0")
    if base is not None:
        changed = ("speed_std_humans_mps", "braking_events_per_veh_h", "energy_kwh_per_100km",
                   "speed_mean_mps")
        ones = ((f, _cell(table, "ring-v1", f, "one vehicle")) for f in families_of(table))
        lines += ["On `ring-v1`, one automated vehicle among 21 IDM humans against the all-human "
                  "ring (changes of the means; humans' speed std, braking events per vehicle "
                  "and hour, energy per vehicle and 100 km of the whole string, mean speed):", "",
                  *table_lines(["family", "collisions", "humans' speed std", "braking events",
                                "energy", "mean speed"],
                               ([f"`{f}`", f"{c['collisions']}/{c['runs']}",
                                 *(_change(c[k], base[k]) for k in changed)]
                                for f, c in ones if c is not None)),
                  "", "Published, for comparison: " + STERN_2018 + "; " + FLOW_2018 + "; "
                  + CIRCLES_2024 + ". A colliding run ends early: read its other columns with "
                  "the collision count.", ""]
    lines += ["Per scenario and share, the family with the smallest humans' speed std (the "
              "last vehicle's at share 1) among the families without a collision:", "",
              *table_lines(["scenario", *(s.name for s in SHARES[1:])], [])]
    for scenario, t in table.groupby("scenario", sort=False):
        best = []
        for share in SHARES[1:]:
            col = "speed_std_last_mps" if share.name == "1" else "speed_std_humans_mps"
            ok = t[(t["share"].astype(str) == share.name) & (t["collisions"] == 0)
                   & (t["controller"] != BASELINE)]
            ok = ok[np.isfinite(ok[col].to_numpy(dtype=np.float64))]
            if ok.empty:
                best.append("none without a collision")
                continue
            r = ok.loc[ok[col].idxmin()]
            best.append(f"`{r['controller']}` ({r[col]:.2f} m/s)")
        lines.append(row([scenario, *best]))
    lines += ["", "The head-to-tail gain is the ratio of the last vehicle's speed std to the "
              "first's (the leader, or follower 1 on the ring): n/a where the first vehicle's "
              "speed does not vary (`catchup-v1`'s leader), and a ratio of two small numbers "
              "where a damper has stilled the ring: read it with the speed stds.", ""]
    return lines


def write_report(table: Any, out: Path, command: str, episodes: int, placements: int,
                 figures: Sequence[Path]) -> Path:
    """``report.md``: the command, the design, a table per scenario and the figures (paths
    relative to ``out``)."""
    from infra.atomic import write_text

    lines = [
        "# Penetration study: which family damps waves at what share of automated vehicles",
        "",
        f"Made by `{command}`. {episodes} test episodes per placement; the mixed shares at "
        f"{placements} seeded random placements each (pooled: a cell's interval covers "
        "placements and episodes), 95 % percentile-bootstrap intervals over episodes. Shares "
        "0 and 1 have one arrangement. The all-human string (every seat the IDM with noise) is "
        "the row at share 0. Metrics are defined in `docs/concepts/metrics.md` (mixed traffic); "
        "on `ring-v1` they leave out the first 60 s.",
        "",
        *findings(table),
    ]
    for scenario, t in table.groupby("scenario", sort=False):
        lines += [f"## {scenario}", "",
                  *table_lines(["controller", "share", "runs", "collisions",
                                *(name for _, name in METRICS)],
                               ([f"`{r['controller']}`", f"{r['share']} ({r['cav_share']:.2f})",
                                 r["runs"], r["collisions"],
                                 *(_fmt(r[c], r[f"{c}_lo"], r[f"{c}_hi"]) for c, _ in METRICS)]
                                for _, r in t.iterrows())), ""]
        for fig in figures:
            if fig.name == f"penetration-{scenario}.png":
                lines += [f"![{scenario}]({fig.relative_to(out).as_posix()})", ""]
    return write_text(out / "report.md", "\n".join(lines) + "\n")

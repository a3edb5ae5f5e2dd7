"""The generalisation matrix: every learned controller (per training scenario or family, training
seeds pooled), with and without the safety filter, beside the model-based controllers, on
scenarios, platoon sizes and V2V settings it was not trained on, on the test seeds.

:data:`COLUMNS` are the test conditions; :func:`matrix_rows` the controllers; a cell holds the
colliding episodes, the mean reward with its two-stage interval over training seeds and
episodes, and the gap RMSE. A controller that cannot act in a column (a per-agent policy at
another N) is "not applicable" there, never silently skipped.
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from analysis.tables import table_lines
from benchmark.statistics import hierarchical_bootstrap_ci

if TYPE_CHECKING:
    from envs.scenarios import Scenario


@dataclass(frozen=True)
class Column:
    """One test condition: scenario (with options), N and V2V."""

    name: str
    scenario: str
    n_vehicles: int = 8
    comm_delay_s: float = 0.0
    packet_loss: float = 0.0

    @cached_property
    def built(self) -> Scenario:
        """The column's scenario, built once (its ``label`` names the column's runs)."""
        from envs.scenarios import make_scenario

        return make_scenario(self.scenario)


COLUMNS: tuple[Column, ...] = (
    Column("catchup", "catchup-v1"),
    Column("slowdown", "slowdown-v1"),
    Column("brake", "brake-v1"),
    Column("sine", "sine-v1"),
    Column("sine 3 m/s 0.1 Hz", "sine-v1:amplitude_mps=3,frequency_hz=0.1"),
    Column("OpenACC S", "openacc-s-v1"),
    Column("OpenACC M", "openacc-m-v1"),
    Column("OpenACC L", "openacc-l-v1"),
    Column("OpenACC S N=4", "openacc-s-v1", n_vehicles=4),
    Column("OpenACC M N=4", "openacc-m-v1", n_vehicles=4),
    Column("OpenACC L N=4", "openacc-l-v1", n_vehicles=4),
    Column("catchup N=4", "catchup-v1", n_vehicles=4),
    Column("catchup N=12", "catchup-v1", n_vehicles=12),
    Column("catchup 0.2 s 30 %", "catchup-v1", comm_delay_s=0.2, packet_loss=0.3),
)

#: Model-based controllers (one row each, no training seed).
MODEL_BASED: tuple[str, ...] = ("cacc", "mpc-qp", "mpc", "cmpc", "acc", "ovm", "duty")
#: Training scenarios of the shipped learned policies at N = 8.
TRAINED_ON: tuple[str, ...] = ("catchup-v1", "slowdown-v1")
#: The training distributions ``ippo`` is shipped trained on (``mixed-v2`` adds the OpenACC-like
#: leader to ``mixed-v1``'s four kinds).
MIXED_FAMILIES: tuple[str, ...] = ("mixed-v1", "mixed-v2")
#: Training seeds pooled in a learned row.
TRAIN_SEEDS: tuple[int, ...] = (0, 1, 2)
#: The N a shared policy's checkpoint is filed under (it acts at any N).
SHARED_TRAINED_N = 8
#: Per-agent policies trained at another N than 8: (algorithm, training scenario or family, N,
#: the training seeds shipped). They act at that N only; one seed each is shipped, so their rows
#: name it instead of pooling three.
OTHER_N_POLICIES: tuple[tuple[str, str, int, tuple[int, ...]], ...] = (
    ("bdc", "catchup-v1", 4, (0,)),
    ("bdc", "openacc-train-s-v1", 4, (0,)),
    ("bdc", "openacc-train-m-v1", 4, (0,)),
    ("bdc", "openacc-train-l-v1", 4, (0,)),
)
#: Shipped checkpoints the matrix does not run, each with why (``fnmatch`` patterns of the path
#: below ``controllers/checkpoints``); the report lists them, so none is left out silently.
NOT_IN_MATRIX: tuple[tuple[str, str], ...] = (
    ("variants/w5_*/*", "the reward-weight variants of the energy-spacing study (w5 = 0, -1, "
                        "-5, -20; seed 0; the same scenario under another reward)"),
    ("bdc__catchup-v1__n2__*", "BDC of the scaling study at N = 2: no column is at its N"),
    ("bdc__catchup-v1__n6__*", "BDC of the scaling study at N = 6: no column is at its N"),
    ("variants/paper/*", "the paper reproduction's own policies (slowdown-v1 at the paper's 6e5 "
                         "steps, the size and OpenACC studies' other seeds), which `cacc-bench "
                         "reproduce` copies and judges in its own report"),
    ("variants/bdc-noqsgd/*", "BDC without QSGD, the paper reproduction's ablation, judged in "
                              "its report"),
    ("variants/class-features/*", "ippo with class features, trained on strings of vehicle "
                                  "classes (one seed), read on a heterogeneous string in "
                                  "docs/learned-control.md"),
    ("variants/mixed-traffic/*", "ippo trained on mixed traffic (humans in the string, the "
                                 "ring), whose study is the penetration study "
                                 "(`cacc-bench penetration`)"),
)


@dataclass(frozen=True)
class Row:
    """A matrix row: label, registered controller, options (without the training seed), whether
    it is learned (pooled over ``seeds``, :data:`TRAIN_SEEDS` unless named) and the N it acts at
    (None: any)."""

    label: str
    controller: str
    options: tuple[tuple[str, str], ...]
    learned: bool
    only_n: int | None = None
    seeds: tuple[int, ...] = TRAIN_SEEDS

    def specs(self) -> list[tuple[str, dict[str, str]]]:
        """The controller specs the row runs (one per training seed for a learned row)."""
        opts = dict(self.options)
        if not self.learned:
            return [(self.controller, opts)]
        return [(self.controller, {**opts, "seed": str(s)}) for s in self.seeds]

    @property
    def trained_n(self) -> int:
        """The N its checkpoints are filed under: its only N, else :data:`SHARED_TRAINED_N`."""
        return SHARED_TRAINED_N if self.only_n is None else self.only_n

    def checkpoints(self) -> list[str]:
        """The shipped checkpoint files a learned row loads, as paths below
        ``controllers/checkpoints`` (``variants/<name>/...`` for a variant); [] if not learned."""
        if not self.learned:
            return []
        from infra.naming import checkpoint_stem

        opts = dict(self.options)
        algo = self.controller.removeprefix("safe:")
        folder = f"variants/{opts['variant']}/" if "variant" in opts else ""
        return [f"{folder}{checkpoint_stem(algo, opts['scenario'], self.trained_n, s)}.pt"
                for s in self.seeds]

    def applies(self, column: Column) -> bool:
        """Whether the controller can act in ``column`` (a per-agent policy at its N only)."""
        return self.only_n is None or self.only_n == column.n_vehicles


def learned_rows(available: Any) -> list[Row]:
    """Every shipped learned policy, per training scenario or family: the paper's seven (one
    network per follower, N = 8 only), the shared policies (any N), ``ippo-bdc`` (N = 8), the
    residual and OVM-gain variants of ``ippo``, ``ippo`` trained on :data:`MIXED_FAMILIES`, then the
    per-agent policies trained at another N (:data:`OTHER_N_POLICIES`, one seed each, named in
    the label); ``available(controller, options, n_vehicles)`` says whether a checkpoint exists
    (rows lacking one are left out by the caller)."""
    from controllers.policy import IPPO_VARIANTS
    from marl.learners import PAPER_ALGORITHMS, PER_AGENT_SHARED, SHARED_LEARNERS

    rows: list[Row] = []
    for algo in (*PAPER_ALGORITHMS, *SHARED_LEARNERS):
        shared = algo in SHARED_LEARNERS and algo not in PER_AGENT_SHARED
        for sc in TRAINED_ON:
            rows.append(Row(f"{algo} ({sc})", algo, (("scenario", sc),), True,
                            None if shared else 8))
    for family in MIXED_FAMILIES:
        rows.append(Row(f"ippo ({family})", "ippo", (("scenario", family),), True))
    for variant in IPPO_VARIANTS:
        for sc in TRAINED_ON:
            rows.append(Row(f"ippo {variant} ({sc})", "ippo",
                            (("scenario", sc), ("variant", variant)), True))
    for algo, sc, n, seeds in OTHER_N_POLICIES:
        named = ", ".join(f"seed {s}" for s in seeds)
        rows.append(Row(f"{algo} ({sc}, N={n}, {named})", algo, (("scenario", sc),), True, n,
                        seeds))
    return [r for r in rows if all(available(c, o, r.trained_n) for c, o in r.specs())]


def unrun_checkpoints(folder: Path, rows: Sequence[Row]) -> dict[str, list[str]]:
    """The shipped checkpoints (``*.pt`` below ``folder``, variants included) that no row of
    ``rows`` loads, by the reason :data:`NOT_IN_MATRIX` gives; a file it does not explain falls
    under ``"no row and no reason"`` (a test keeps that empty)."""
    from fnmatch import fnmatch

    loaded = {f for r in rows for f in r.checkpoints()}
    out: dict[str, list[str]] = {}
    for path in sorted(folder.rglob("*.pt")):
        rel = path.relative_to(folder).as_posix()
        if rel in loaded:
            continue
        why = next((w for pattern, w in NOT_IN_MATRIX if fnmatch(rel, pattern)),
                   "no row and no reason")
        out.setdefault(why, []).append(rel)
    return out


def with_safety_filter(row: Row) -> Row:
    """The same controller behind the safety filter (``safe:<controller>``)."""
    return Row(f"safe:{row.label}", f"safe:{row.controller}", row.options, row.learned,
               row.only_n, row.seeds)


def cell_frame(runs: Any, rows: list[Row], columns: Sequence[Column] = COLUMNS) -> Any:
    """One row per matrix row and column: applicable, episodes, collisions, reward mean and
    interval (two-stage over training seeds, then episodes), gap RMSE."""
    import pandas as pd

    from controllers.registry import controller_label

    ok = runs[runs["status"] == "ok"]
    out = []
    for row in rows:
        labels = [controller_label(c, o) for c, o in row.specs()]
        for col in columns:
            rec: dict[str, Any] = {"row": row.label, "column": col.name, "applicable": row.applies(col)}
            if not rec["applicable"]:
                out.append(rec)
                continue
            sel = ok[ok["controller"].isin(labels) & (ok["scenario"] == col.built.label)
                     & (ok["n_vehicles"] == col.n_vehicles)
                     & np.isclose(ok["comm_delay_s"], col.comm_delay_s)
                     & np.isclose(ok["packet_loss"], col.packet_loss)]
            groups = [sel[sel["controller"] == lab]["reward"].to_numpy(float) for lab in labels]
            mean, lo, hi = hierarchical_bootstrap_ci(groups, seed=20240601)
            rec.update(episodes=int(len(sel)), collisions=int(sel["collision"].astype(bool).sum()),
                       reward=mean, reward_ci_low=lo, reward_ci_high=hi,
                       gap_rmse_m=float(sel["gap_rmse_m"].mean()),  # NaN without episodes
                       energy_kwh_per_100km=float(sel["energy_kwh_per_100km"].mean()),
                       safety_interventions=float(sel["safety_interventions"].mean())
                       if "safety_interventions" in sel else math.nan)
            out.append(rec)
    return pd.DataFrame(out)


def plot_heatmap(cells: Any, out: Path, columns: Sequence[Column] = COLUMNS) -> list[Path]:
    """Collision share per cell (colour; grey: not applicable), mean reward as the cell's text."""
    from analysis.plots import _plt, save_figure

    plt = _plt()
    rows = list(dict.fromkeys(cells["row"]))
    cols = [c.name for c in columns]
    share = np.full((len(rows), len(cols)), np.nan)
    text = [["n/a"] * len(cols) for _ in rows]
    for _, c in cells.iterrows():
        i, j = rows.index(c["row"]), cols.index(c["column"])
        if c["applicable"] and c.get("episodes", 0):
            share[i, j] = c["collisions"] / c["episodes"]
            text[i][j] = f"{c['reward']:.0f}"
    fig, ax = plt.subplots(figsize=(1.0 * len(cols) + 3, 0.28 * len(rows) + 1.5))
    cmap = plt.get_cmap("Reds").copy()
    cmap.set_bad("#dddddd")
    im = ax.imshow(np.ma.masked_invalid(share), cmap=cmap, vmin=0, vmax=1, aspect="auto")
    ax.set_xticks(range(len(cols)), cols, rotation=40, ha="right", fontsize=7)
    ax.set_yticks(range(len(rows)), rows, fontsize=6)
    for i in range(len(rows)):
        for j in range(len(cols)):
            ax.text(j, i, text[i][j], ha="center", va="center", fontsize=5)
    fig.colorbar(im, ax=ax, label="colliding share of episodes")
    ax.set_title("reward (text) and collisions (colour) on the test seeds", fontsize=8)
    paths = save_figure(fig, out, "generalisation", dpi=100, bbox_inches="tight")
    plt.close(fig)
    return paths


def write_report(cells: Any, out: Path, command: str, episodes: int,
                 columns: Sequence[Column] = COLUMNS,
                 unrun: dict[str, list[str]] | None = None) -> Path:
    """``report.md``: the matrix (collisions / episodes, reward [interval], gap RMSE per cell),
    what the safety filter costs, and the shipped checkpoints no row runs (``unrun``, by reason,
    from :func:`unrun_checkpoints`)."""
    from infra.atomic import write_text

    cols = [c.name for c in columns]
    lines = [
        "# Generalisation matrix",
        "",
        f"Made by `{command} --out FOLDER` on the first {episodes} test seeds "
        "(`envs.params.TEST_SEEDS`, which no training, tuning or selection reads). Rows: "
        "learned controllers by training scenario or family, three training seeds pooled "
        "(a row that names a seed has only that one shipped, and its interval is over episodes "
        "alone), actions sampled as trained, with and without the safety filter (`safe:`), then "
        "the model-based controllers. A cell: colliding episodes / episodes, mean reward [95 % "
        "two-stage interval], gap RMSE in m; \"n/a\": the controller cannot act at that N. "
        "Columns use N = 8 unless named; the OpenACC windows run also at N = 4, their "
        "scenarios' default and the N the OpenACC-like families' policies were trained at. "
        "Tables: `matrix.csv`; figure: "
        "`figures/generalisation.png`.",
        "",
        "![matrix](figures/generalisation.png)",
        "",
    ]

    def cell(r: Any) -> str:
        if not r["applicable"]:
            return "n/a"
        if not r.get("episodes", 0):
            return "not run"
        return (f"{int(r['collisions'])}/{int(r['episodes'])}, {r['reward']:.1f} "
                f"[{r['reward_ci_low']:.1f}, {r['reward_ci_high']:.1f}], {r['gap_rmse_m']:.2f}")

    matrix = []
    for row, grp in cells.groupby("row", sort=False):
        by = {r["column"]: r for _, r in grp.iterrows()}
        matrix.append([f"`{row}`", *(cell(by[c]) for c in cols)])
    lines += table_lines(["controller", *cols], matrix)
    cost = filter_cost(cells)
    if len(cost):
        lines += ["", "## What the safety filter costs", "",
                  "Per learned row: colliding episodes without and with the filter over the "
                  "matrix, and, in the cells where the row collided in no episode without it, the "
                  "mean change of reward and of energy (kWh/100 km) the filter makes. Table: "
                  "`filter_cost.csv`.", "",
                  *table_lines(["controller", "collisions without", "with", "clean cells",
                                "reward change", "energy change kWh/100 km"],
                               ([f"`{r['row']}`", r["collisions_without"], r["collisions_with"],
                                 r["clean_cells"], f"{r['reward_change']:+.1f}",
                                 f"{r['energy_change_kwh_per_100km']:+.3f}"]
                                for _, r in cost.iterrows()))]
    if unrun:
        lines += ["", "## Shipped checkpoints not in the matrix", "",
                  "Every file of `controllers/checkpoints` that no row above loads, with why "
                  "(`studies.generalisation.NOT_IN_MATRIX`):", ""]
        lines += [f"- {why}: " + ", ".join(f"`{f}`" for f in files) for why, files in unrun.items()]
    return write_text(out / "report.md", "\n".join(lines) + "\n")


def filter_cost(cells: Any) -> Any:
    """Per learned row: in the cells where it collided in no episode without the filter, the
    mean change the safety filter makes to the reward and to the energy (kWh/100 km); and the
    colliding episodes it removed elsewhere."""
    import pandas as pd

    c = cells[cells["applicable"]].set_index(["row", "column"])
    out = []
    for row in dict.fromkeys(cells["row"]):
        if row.startswith("safe:") or f"safe:{row}" not in c.index.get_level_values(0):
            continue
        plain, safe = c.loc[row], c.loc[f"safe:{row}"]
        clean = plain["collisions"] == 0
        out.append({"row": row, "clean_cells": int(clean.sum()),
                    "reward_change": float((safe["reward"] - plain["reward"])[clean].mean()),
                    "energy_change_kwh_per_100km": float(
                        (safe["energy_kwh_per_100km"] - plain["energy_kwh_per_100km"])[clean].mean()),
                    "collisions_without": int(plain["collisions"].sum()),
                    "collisions_with": int(safe["collisions"].sum())})
    return pd.DataFrame(out)


def rows_json(rows: list[Row]) -> str:
    """The rows as JSON (what the command ran), for the report folder."""
    return json.dumps([{"label": r.label, "controller": r.controller,
                        "options": dict(r.options), "learned": r.learned,
                        "only_n": r.only_n, "training_seeds": list(r.seeds) if r.learned else []}
                       for r in rows], indent=1)

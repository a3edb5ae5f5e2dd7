"""BDC-MARL's sensitivity to its knobs and to V2V degradation (``cacc-bench sensitivity``).

Pure functions of ``runs.csv`` rows and the training summaries: one row per scenario, knob and
value with intervals over episodes (and training seeds, two-stage, when there are several),
the bits each variant sent in training, and the figures.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from benchmark.statistics import hierarchical_bootstrap_ci

#: Metrics with a 95 % interval in :data:`SENSITIVITY_COLUMNS`.
METRICS: tuple[str, ...] = ("reward", "energy_kwh_per_100km", "gap_rmse_m")

SENSITIVITY_COLUMNS: tuple[str, ...] = (
    "scenario", "knob", "knob_value", "variant", "is_base",
    *(f"{m}_{s}" for m in METRICS for s in ("mean", "ci_low", "ci_high")),
    "collisions", "n_episodes", "n_seeds", "execution_bits_per_vehicle_per_s",
    "training_bits_sent_per_agent", "qsgd_payload_bits_per_agent",
)


def training_bits(summary: dict[str, float]) -> tuple[float, float]:
    """Bits one agent sent in a training run (per-step messages over every step, plus the
    consensus rounds) and the QSGD payload it would have sent (applied locally, not sent)."""
    sent = (summary.get("training_step_bits_per_agent_step", 0.0) * summary.get("total_steps", 0.0)
            + summary.get("training_consensus_bits_per_agent", 0.0))
    return float(sent), float(summary.get("local_qsgd_payload_bits_per_agent", 0.0))


def sensitivity_frame(runs: Any, settings: Sequence[dict[str, Any]]) -> Any:
    """One row per scenario and setting (see :data:`SENSITIVITY_COLUMNS`).

    Parameters
    ----------
    runs : DataFrame
        ``runs.csv`` rows with status ok.
    settings : sequence of dict
        ``scenario``, ``knob``, ``knob_value``, ``variant``, ``is_base``, ``labels`` (the
        leaderboard label of each training seed's policy), ``comm_delay_s``, ``packet_loss`` and
        ``training`` (one curve summary per seed, see :func:`training_bits`; empty for
        references that did not train).
    """
    import pandas as pd

    rows = []
    for s in settings:
        sub = runs[(runs["scenario"] == s["scenario"]) & runs["controller"].isin(s["labels"])
                   & np.isclose(runs["comm_delay_s"], s["comm_delay_s"])
                   & np.isclose(runs["packet_loss"], s["packet_loss"])]
        if sub.empty:
            continue
        groups = [g for _, g in sub.groupby("controller", sort=True)]
        row = {k: s[k] for k in ("scenario", "knob", "knob_value", "variant", "is_base")}
        for metric in METRICS:
            m, lo, hi = hierarchical_bootstrap_ci([g[metric].to_numpy(float) for g in groups])
            row.update({f"{metric}_mean": m, f"{metric}_ci_low": lo, f"{metric}_ci_high": hi})
        row["collisions"] = int(sub["collision"].sum())
        row["n_episodes"] = len(sub)
        row["n_seeds"] = len(groups)
        row["execution_bits_per_vehicle_per_s"] = float(sub["comm_bits_per_s"].mean()
                                                        / sub["n_vehicles"].iloc[0])
        bits = [training_bits(t) for t in s["training"]]
        row["training_bits_sent_per_agent"] = float(np.mean([b[0] for b in bits])) if bits else np.nan
        row["qsgd_payload_bits_per_agent"] = float(np.mean([b[1] for b in bits])) if bits else np.nan
        rows.append(row)
    return pd.DataFrame(rows, columns=list(SENSITIVITY_COLUMNS))


def knob_effects(df: Any) -> Any:
    """Per scenario and knob: the spread of mean reward over its values, the best and worst
    value, and whether any value's interval lies wholly off the unchanged policy's."""
    import pandas as pd

    out = []
    for (scenario, knob), g in df[df["knob"] != "reference"].groupby(["scenario", "knob"],
                                                                      sort=False):
        base = g[g["is_base"]]
        best = g.loc[g["reward_mean"].idxmax()]
        worst = g.loc[g["reward_mean"].idxmin()]
        separated = False
        if not base.empty:
            b = base.iloc[0]
            others = g[~g["is_base"]]
            separated = bool(((others["reward_ci_high"] < b["reward_ci_low"])
                              | (others["reward_ci_low"] > b["reward_ci_high"])).any())
        out.append({"scenario": scenario, "knob": knob,
                    "reward_spread": float(g["reward_mean"].max() - g["reward_mean"].min()),
                    "best_value": best["knob_value"], "best_reward": float(best["reward_mean"]),
                    "worst_value": worst["knob_value"], "worst_reward": float(worst["reward_mean"]),
                    "collisions": int(g["collisions"].sum()),
                    "differs_from_base": separated})
    return pd.DataFrame(out)


def plot_sensitivity(df: Any, scenario: str, out_dir: Path, stem: str) -> list[Path]:
    """Mean reward with its 95 % interval against each knob's values (one panel per knob; the
    unchanged policy in black, the number of collided episodes above each point, the reference
    controllers as dashed lines)."""
    from analysis.plots import _plt, _save

    plt = _plt()
    ref = df[(df["scenario"] == scenario) & (df["knob"] == "reference")]
    sub = df[(df["scenario"] == scenario) & (df["knob"] != "reference")]
    knobs = list(dict.fromkeys(sub["knob"]))
    fig, axes = plt.subplots(1, max(len(knobs), 1), figsize=(3.0 * max(len(knobs), 1), 3.4),
                             sharey=True, squeeze=False)
    for ax, knob in zip(axes[0], knobs, strict=False):
        g = sub[sub["knob"] == knob].reset_index(drop=True)
        x = np.arange(len(g))
        y = g["reward_mean"].to_numpy()
        err = np.abs(np.vstack([y - g["reward_ci_low"], g["reward_ci_high"] - y]))
        colors = ["black" if b else "tab:blue" for b in g["is_base"]]
        for xi, yi, e0, e1, c in zip(x, y, err[0], err[1], colors, strict=True):
            ax.errorbar([xi], [yi], yerr=[[e0], [e1]], color=c, marker="o", capsize=3)
        for xi, yi, n in zip(x, g["reward_ci_high"], g["collisions"], strict=True):
            if n:
                ax.annotate(f"{n} coll.", (xi, yi), fontsize=7, ha="center", va="bottom",
                            color="tab:red")
        ax.set_xticks(x, [str(v) for v in g["knob_value"]], fontsize=7, rotation=30)
        ax.set_title(knob, fontsize=9)
        for _, r in ref.iterrows():
            ax.axhline(r["reward_mean"], color="grey", ls="--", lw=1)
            ax.annotate(r["variant"], (0, r["reward_mean"]), fontsize=7, color="grey",
                        xytext=(0, 2), textcoords="offset points")
        ax.grid(alpha=0.3)
    axes[0][0].set_ylabel("reward per step (benchmark score)")
    fig.suptitle(f"BDC-MARL, one knob at a time, on {scenario} (black: unchanged policy)",
                 fontsize=10)
    return _save(fig, out_dir, stem)


def plot_bits_against_reward(df: Any, out_dir: Path, stem: str) -> list[Path]:
    """The communication-versus-performance curve: training bits per agent against final
    reward, one marker per trained variant; hollow markers add the QSGD payload that the paper's
    bandwidth argument counts (applied locally here, not sent)."""
    from analysis.plots import _plt, _save

    plt = _plt()
    trained = df[np.isfinite(df["training_bits_sent_per_agent"].to_numpy(float))
                 & ~df["knob"].str.startswith("v2v")].drop_duplicates(["scenario", "variant"])
    fig, ax = plt.subplots(figsize=(7, 4.5))
    for j, (scenario, g) in enumerate(trained.groupby("scenario", sort=True)):
        color = plt.get_cmap("tab10")(j)
        ax.scatter(g["training_bits_sent_per_agent"], g["reward_mean"], color=color,
                   label=f"{scenario}: sent")
        with_qsgd = g["training_bits_sent_per_agent"] + g["qsgd_payload_bits_per_agent"]
        ax.scatter(with_qsgd, g["reward_mean"], facecolors="none", edgecolors=color,
                   label=f"{scenario}: sent + QSGD payload")
        for xv, yv, name in zip(g["training_bits_sent_per_agent"], g["reward_mean"],
                                g["variant"], strict=True):
            ax.annotate(name, (xv, yv), fontsize=6, xytext=(3, 3), textcoords="offset points")
    ax.set_xscale("log")
    ax.set_xlabel("training bits per agent (whole run)")
    ax.set_ylabel("reward per step (benchmark score)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    return _save(fig, out_dir, stem)


def write_report(df: Any, out: Path, command: str, steps: int, seeds: list[int],
                 episodes: int) -> Path:
    """``OUT/report.md`` with a table per scenario, the knob effects and the figures."""
    from analysis.tables import format_table
    from benchmark.export import write_csv
    from benchmark.provenance import git_sha
    from infra.atomic import write_text

    fig_dir = out / "figures"
    lines = ["# BDC-MARL sensitivity", "",
             f"Command: `{command}` (git {git_sha()}). Each variant trained with seed(s) "
             f"{', '.join(map(str, seeds))} for {steps:,} steps from the tuned config, one knob "
             f"changed; evaluated on the first {episodes} published evaluation seeds, actions "
             "sampled. Intervals: 95 % bootstrap over episodes (and seeds, two-stage, when "
             "there are several). Training bits: what one agent sent in its run (per-step "
             "messages plus consensus rounds); the QSGD payload is applied locally, not sent.",
             ""]
    cols = [("knob", "knob"), ("knob_value", "value"), ("collisions", "collisions"),
            ("reward_mean", "reward"), ("reward_ci_low", "low"), ("reward_ci_high", "high"),
            ("energy_kwh_per_100km_mean", "kWh/100 km"), ("gap_rmse_m_mean", "gap RMSE m"),
            ("training_bits_sent_per_agent", "training bits sent"),
            ("qsgd_payload_bits_per_agent", "QSGD payload bits")]

    def values(column: Any) -> list[str]:  # a knob's values as the tables print them
        return [f"{v:.3g}" if isinstance(v, float) else str(v) for v in column]

    shown = df.assign(knob_value=values(df["knob_value"]))
    for sc in dict.fromkeys(df["scenario"]):
        plot_sensitivity(df, sc, fig_dir, f"sensitivity__{sc}")
        lines += [f"## {sc}", "", format_table(shown[shown["scenario"] == sc], cols, 3), "",
                  f"![sensitivity on {sc}](figures/sensitivity__{sc}.png)", ""]
    effects = knob_effects(df)
    write_csv(effects, out / "knob_effects.csv")
    effects = effects.assign(best_value=values(effects["best_value"]),
                             worst_value=values(effects["worst_value"]))
    plot_bits_against_reward(df, fig_dir, "bits_against_reward")
    lines += ["## Which knob matters", "",
              "Spread: the largest minus the smallest mean reward over the knob's values; "
              "'differs' when some value's interval lies wholly off the unchanged policy's.", "",
              format_table(effects, [("scenario", "scenario"), ("knob", "knob"),
                                     ("reward_spread", "spread"), ("best_value", "best"),
                                     ("worst_value", "worst"), ("collisions", "collisions"),
                                     ("differs_from_base", "differs")], 1), "",
              "## Communication against performance", "",
              "![training bits against reward](figures/bits_against_reward.png)"]
    return write_text(out / "report.md", "\n".join(lines) + "\n")

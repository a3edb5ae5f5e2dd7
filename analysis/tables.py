"""Markdown tables of a leaderboard (for READMEs and notes, from runs one has made)."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

Column = tuple[str, Callable[[Any], str]]


def _ci(metric: str, digits: int = 2) -> Callable[[Any], str]:
    def fmt(r: Any) -> str:
        return (f"{r[metric + '_mean']:.{digits}f} [{r[metric + '_ci_low']:.{digits}f}, "
                f"{r[metric + '_ci_high']:.{digits}f}]")

    return fmt


def _mean(metric: str, digits: int) -> Callable[[Any], str]:
    return lambda r: f"{r[metric + '_mean']:.{digits}f}"


DEFAULT_COLUMNS: tuple[Column, ...] = (
    ("scenario", lambda r: str(r["scenario"])),
    ("rank", lambda r: str(int(r["rank"]))),
    ("controller", lambda r: f"`{r['controller']}`"),
    ("collisions", lambda r: f"{int(r['collisions'])}/{int(r['n_episodes'])}"),
    ("reward [95% CI]", _ci("reward")),
    ("tracking", _mean("tracking_reward", 2)),
    ("energy kWh", _mean("energy_kwh", 3)),
    ("gap RMSE m", _mean("gap_rmse_m", 2)),
    ("jerk RMS m/s^3", _mean("jerk_rms_mps3", 2)),
    ("string gain", _mean("string_gain", 3)),
    ("ms/veh/step", _mean("compute_ms_p50", 3)),
    ("V2V bit/s", _mean("comm_bits_per_s", 0)),
)


def markdown_leaderboard(lb: Any, columns: Sequence[Column] = DEFAULT_COLUMNS) -> str:
    """A Markdown table of a leaderboard DataFrame, one row per controller x setting."""
    head = "| " + " | ".join(name for name, _ in columns) + " |"
    rule = "|" + "---|" * len(columns)
    rows = ["| " + " | ".join(fmt(r) for _, fmt in columns) + " |" for _, r in lb.iterrows()]
    return "\n".join([head, rule, *rows])


def format_leaderboard(lb: Any) -> str:
    """The leaderboard as a plain-text table with a note on what the intervals mean."""
    if len(lb) == 0:
        return "(no runs)"
    lines = []
    sw = max(14, *(len(str(x)) for x in lb["scenario"]))
    cw = max(22, *(len(str(x)) + 1 for x in lb["controller"]))  # labels are never cut
    head = (f"{'rank':>4}  {'controller':<{cw}} {'scenario':<{sw}} {'N':>2} {'eps':>3} {'coll':>4} "
            f"{'fail':>4}  {'reward [95% CI]':<26} {'tracking':>9} {'kWh':>7} {'gap rmse':>8} "
            f"{'str.gain':>8} {'ms/veh':>7} {'bit/s':>7}")
    setting_cols = ["comm_delay_s", "packet_loss", "lag_s"]
    for setting, grp in lb.groupby(setting_cols, sort=True):
        d, loss, lag = setting
        lines.append(f"\nV2V delay {d:g} s, packet loss {loss:g}, actuator lag {lag:g} s")
        lines.append(head)
        for _, r in grp.iterrows():
            ci = f"{r['reward_mean']:.2f} [{r['reward_ci_low']:.2f}, {r['reward_ci_high']:.2f}]"
            det = "" if r.get("deterministic") in (True, None) else "*"
            lines.append(
                f"{int(r['rank']):>4}  {str(r['controller']) + det:<{cw}} {r['scenario']:<{sw}} "
                f"{int(r['n_vehicles']):>2} {int(r['n_episodes']):>3} {int(r['collisions']):>4} "
                f"{int(r['failed']):>4}  {ci:<26} {r['tracking_reward_mean']:>9.2f} "
                f"{r['energy_kwh_mean']:>7.3f} {r['gap_rmse_m_mean']:>8.2f} "
                f"{r['string_gain_mean']:>8.3f} {r['compute_ms_p50_mean']:>7.3f} "
                f"{r['comm_bits_per_s_mean']:>7.0f}"
            )
    lines.append(
        "\nreward = mean over steps of the sum over agents (higher is better); rank: runs without"
        " collision or failure first, then by reward. Deterministic controllers vary only through"
        " the scenario's perturbation, so their intervals are episode variation, not training"
        " variance; stochastic ones (sampled MARL policies) are marked *. A row over several"
        " training seeds (seeds=0+1+2) has a two-stage bootstrap interval: seeds, then episodes."
    )
    scen = set(lb["scenario"])
    if "openacc-m-v1" in scen:
        from envs.scenarios import make_scenario

        lines.append(make_scenario("openacc-m-v1").note)
    return "\n".join(lines)

"""The rules that turn measurements into claim verdicts (``docs/claim-rules.md``).

One rule per kind of claim, each a pure function of hand-checkable inputs:

* convergence (:func:`convergence_step`): the first evaluation after which a validation curve
  stays within a band of its final plateau; a curve that never rises above its start, or that is
  still outside the band on its plateau, has not converged (``NaN``);
* comparisons (:func:`compare`): safety first, read from the leaderboard's own rows
  (:func:`safety_of`, :func:`benchmark.export.leaderboard_frame`: no collision and no failed
  run ranks first), then a paired two-stage interval over training seeds and episodes
  (:func:`benchmark.statistics.paired_ci`); "inconclusive" whenever that interval covers 0;
* a claim against several rivals (:func:`all_ahead`), a claim with two halves
  (:func:`both_halves`), "same performance" (:func:`not_worse`), a magnitude
  (:func:`magnitude`) and a rate bound such as "low or zero collisions" (:func:`rate_at_most`).

The verdicts are the four words of :data:`VERDICTS`.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from benchmark.statistics import hierarchical_bootstrap_ci, paired_ci

HOLDS, DOES_NOT_HOLD, INCONCLUSIVE, NOT_TESTABLE = (
    "holds", "does not hold", "inconclusive", "not testable here")

#: Every verdict a claim can get.
VERDICTS: tuple[str, ...] = (HOLDS, DOES_NOT_HOLD, INCONCLUSIVE, NOT_TESTABLE)

#: Half-width of the convergence band, as a fraction of the curve's rise (plateau - first).
CONVERGENCE_BAND = 0.1

#: Validation points averaged for a curve's final plateau; all of them must lie in the band.
PLATEAU_POINTS = 3

#: Converged seeds each side needs before the interval over seeds may decide a convergence
#: comparison (a single seed has no spread to draw).
MIN_CONVERGED_SEEDS = 2

#: "The same performance" (non-inferiority): ours may trail by at most this fraction of the
#: other side's mean magnitude (``|mean of the other|``).
SAME_PERFORMANCE_MARGIN = 0.05

#: "Low" collisions: at most one episode in 50 (the paper's number of test trials).
LOW_COLLISION_RATE = 1.0 / 50.0

Better = Literal["higher", "lower"]
Winner = Literal["ours", "other", "neither"]


# ------------------------------------------------------------------------------ convergence
def convergence_step(steps: np.ndarray, values: np.ndarray, band: float = CONVERGENCE_BAND,
                     plateau_points: int = PLATEAU_POINTS) -> float:
    """First step after which a validation curve stays within ``band`` of its final plateau.

    The plateau is the mean of the last ``plateau_points`` values and the rise is
    ``plateau - values[0]``. The curve has converged at the first evaluation from which every
    later value lies within ``band * rise`` of the plateau (both sides), provided that this
    holds on the whole plateau window (the last ``plateau_points`` values).

    Parameters
    ----------
    steps, values : 1-D arrays
        Training steps and validation reward (higher is better) of one curve, in step order.
    band : float
        Half-width of the band as a fraction of the rise.
    plateau_points : int
        Values averaged for the plateau.

    Returns
    -------
    float
        The step, or ``NaN`` (not converged) when the curve is empty, shorter than the plateau
        window, never rises above its first value (``rise <= 0``: a curve whose plateau is at or
        below its start has learned nothing to converge to), or leaves the band inside the
        plateau window (still moving when training stopped).
    """
    v = np.asarray(values, dtype=float)
    s = np.asarray(steps, dtype=float)
    if v.size < max(plateau_points, 1) or v.size != s.size:
        return math.nan
    plateau = float(np.mean(v[-plateau_points:]))
    rise = plateau - float(v[0])
    if not rise > 0:
        return math.nan
    inside = np.abs(v - plateau) <= band * rise
    outside = np.flatnonzero(~inside)
    first = 0 if outside.size == 0 else int(outside[-1]) + 1
    if first > v.size - plateau_points:
        return math.nan
    return float(s[first])


def converged(steps_per_seed: Iterable[float]) -> tuple[list[float], int]:
    """The converged seeds of a list of convergence steps.

    Parameters
    ----------
    steps_per_seed : iterable of float
        :func:`convergence_step` per training seed.

    Returns
    -------
    steps, not_converged : list of float, int
        The finite steps, and how many seeds did not converge (NaN).
    """
    values = list(steps_per_seed)
    ok = [float(v) for v in values if math.isfinite(v)]
    return ok, len(values) - len(ok)


# ------------------------------------------------------------------------------ safety
@dataclass(frozen=True)
class Safety:
    """Collisions and failed runs of one controller in one setting, as the leaderboard counts."""

    episodes: int
    collisions: int
    failed: int

    @property
    def flaws(self) -> int:
        """Episodes that keep the controller off the leaderboard's clean group."""
        return self.collisions + self.failed

    def text(self) -> str:
        """``'3 coll.'`` (and failed runs when there are any)."""
        return f"{self.collisions} coll." + (f", {self.failed} failed" if self.failed else "")


#: Run columns the leaderboard needs that a hand-made table may lack, with neutral defaults.
_LEADERBOARD_DEFAULTS: dict[str, Any] = {
    "n_vehicles": 0, "comm_delay_s": 0.0, "packet_loss": 0.0, "lag_s": 0.0, "status": "ok",
    "family": "marl", "deterministic": True, "solver_failures": 0, "string_stable": True,
    "collision": False,
}


def safety_of(runs: Any, labels: Mapping[str, str]) -> dict[tuple[str, str, int], Safety]:
    """Collisions and failed runs per (name, scenario, N), read from the leaderboard's rows.

    The leaderboard (:func:`benchmark.export.leaderboard_frame`) ranks the controllers with no
    collision and no failed run first, then by reward; a claim reuses that first key. The runs
    of all labels that map to one name (its training seeds) form one leaderboard row.

    Parameters
    ----------
    runs : DataFrame
        ``runs.csv`` rows; columns the leaderboard needs and the table lacks get neutral
        defaults (no V2V degradation, status ok, no collision), metrics NaN.
    labels : mapping
        Controller label -> name; other labels are left out.
    """
    from benchmark.export import LEADERBOARD_METRICS, leaderboard_frame

    sub = runs[runs["controller"].isin(list(labels))].copy()
    if sub.empty:
        return {}
    sub["controller"] = sub["controller"].map(labels)
    for col, default in _LEADERBOARD_DEFAULTS.items():
        if col not in sub:
            sub[col] = default
    for col in LEADERBOARD_METRICS:
        if col not in sub:
            sub[col] = math.nan
    lb = leaderboard_frame(sub)
    return {(str(r["controller"]), str(r["scenario"]), int(r["n_vehicles"])):
            Safety(int(r["n_episodes"]), int(r["collisions"]), int(r["failed"]))
            for _, r in lb.iterrows()}


# ------------------------------------------------------------------------------ comparisons
@dataclass(frozen=True)
class Comparison:
    """Ours against another on one measure: the interval, the flaws and who is ahead.

    ``mean, low, high`` is the paired statistic (``ours - other``, or the saving in %) and its
    interval; ``winner`` is ``"ours"``, ``"other"`` or ``"neither"``; ``basis`` says what
    decided it.
    """

    mean: float
    low: float
    high: float
    better: Better
    ours_flaws: int
    other_flaws: int
    winner: Winner
    basis: str

    @property
    def by_flaws(self) -> bool:
        """Whether the flaws (rule 1 of :func:`compare`) decided, not the interval."""
        return (self.ours_flaws == 0) != (self.other_flaws == 0)

    def interval(self, digits: int = 1, unit: str = "") -> str:
        """``'+1.0 [+0.5, +1.5]'`` (with ``unit`` after the mean); ``'no interval'`` when the
        flaws decided with nothing to compare."""
        if not math.isfinite(self.mean):
            return "no interval"
        u = f" {unit}" if unit else ""
        return (f"{self.mean:+.{digits}f}{u} [{self.low:+.{digits}f}, {self.high:+.{digits}f}]")

    def oriented(self) -> tuple[float, float, float]:
        """Mean and interval with the sign turned so that positive is better for ours."""
        if self.better == "higher":
            return self.mean, self.low, self.high
        return -self.mean, -self.high, -self.low


def compare(ours: np.ndarray, other: np.ndarray, *, statistic: str = "difference",
            better: Better = "higher", ours_flaws: int = 0, other_flaws: int = 0,
            flaw: str = "collision") -> Comparison:
    """The rule of every comparison: flaws (collisions) first, then the paired interval.

    1. If exactly one side is free of flaws (no collision and no failed run, the leaderboard's
       first key; for convergence: every seed converged), that side is ahead, whatever the
       measure says.
    2. Otherwise the paired two-stage interval over training seeds and episodes
       (:func:`benchmark.statistics.paired_ci`) decides: the side it favours is ahead when it
       excludes 0; when it covers 0, neither is ("inconclusive").
    3. When both sides have flaws, the side the interval favours must not have more of them:
       otherwise neither is ahead (a rival with more collisions never wins a claim).

    Parameters
    ----------
    ours, other : (seeds, episodes) arrays
        The measure per training seed and episode, same episodes in the same order.
    statistic : {"difference", "saving"}
        As :func:`benchmark.statistics.paired_ci`: ``ours - other`` or ``100 (other - ours) /
        other`` in %.
    better : {"higher", "lower"}
        Which sign of the statistic favours ours ("saving" and a reward difference: higher;
        a difference of steps or of a spread: lower).
    ours_flaws, other_flaws : int
        Collisions plus failed runs (or non-converged seeds) of each side.
    flaw : str
        The flaw's name in ``basis``.
    """
    mean, low, high = paired_ci(ours, other, statistic)
    interval_winner: Winner
    if better == "higher":
        interval_winner = "ours" if low > 0 else "other" if high < 0 else "neither"
    else:
        interval_winner = "ours" if high < 0 else "other" if low > 0 else "neither"
    args = (mean, low, high, better, ours_flaws, other_flaws)
    if (ours_flaws == 0) != (other_flaws == 0):
        side: Winner = "ours" if ours_flaws == 0 else "other"
        return Comparison(*args, side, f"no {flaw}s first")
    if interval_winner == "neither":
        return Comparison(*args, "neither", "interval covers 0")
    more = ours_flaws > other_flaws if interval_winner == "ours" else other_flaws > ours_flaws
    if more:
        return Comparison(*args, "neither", f"ahead on the interval but more {flaw}s")
    return Comparison(*args, interval_winner, "interval")


def compare_steps(ours: Sequence[float], other: Sequence[float]) -> Comparison:
    """:func:`compare` for convergence steps per training seed (``NaN``: not converged).

    The flaws are the seeds that did not converge; the interval is over the converged seeds
    (one value each: the bootstrap draws training seeds only), lower is better. A side with
    some converged seeds is ahead of one with none; with none on either side, neither is; and
    when the flaws do not decide, an interval needs at least :data:`MIN_CONVERGED_SEEDS`
    converged seeds on each side (one seed has no spread to draw), else neither is ahead.
    """
    a, na = converged(ours)
    b, nb = converged(other)

    def without_interval(winner: Winner, basis: str) -> Comparison:
        return Comparison(math.nan, math.nan, math.nan, "lower", na, nb, winner, basis)

    if not a or not b:
        if not a and not b:
            return without_interval("neither", "no converged seed on either side")
        if (na == 0) != (nb == 0):
            return without_interval("ours" if na == 0 else "other", "no non-converged seeds first")
        return without_interval("ours" if a else "other", "converged seeds against none")
    if (na == 0) == (nb == 0) and min(len(a), len(b)) < MIN_CONVERGED_SEEDS:
        return without_interval("neither",
                                f"fewer than {MIN_CONVERGED_SEEDS} converged seeds on a side")
    return compare(np.array(a)[:, None], np.array(b)[:, None], better="lower", ours_flaws=na,
                   other_flaws=nb, flaw="non-converged seed")


def all_ahead(comparisons: Mapping[str, Comparison]) -> tuple[str, str]:
    """Verdict of "ours is ahead of every rival".

    Parameters
    ----------
    comparisons : mapping
        Rival name -> :class:`Comparison` of ours against it.

    Returns
    -------
    verdict, reason : str
        Holds if ours is ahead of each rival, does not hold if any rival is ahead, else
        inconclusive (not testable with no rival); the reason names the rivals and what decided.
    """
    if not comparisons:
        return NOT_TESTABLE, "no rival to compare with"
    behind = [r for r, c in comparisons.items() if c.winner == "other"]
    open_ = [r for r, c in comparisons.items() if c.winner == "neither"]
    if behind:
        return DOES_NOT_HOLD, "; ".join(f"{r} ahead ({comparisons[r].basis})" for r in behind)
    if open_:
        return INCONCLUSIVE, "; ".join(f"{r}: {comparisons[r].basis}" for r in open_)
    return HOLDS, "ahead of " + ", ".join(f"{r} ({c.basis})" for r, c in comparisons.items())


def not_worse(c: Comparison, margin: float) -> tuple[str, str]:
    """Verdict of "ours keeps the other's performance" (non-inferiority within ``margin``).

    Parameters
    ----------
    c : Comparison
        Ours against the other.
    margin : float
        How far ours may trail, in the units of ``c``'s statistic (positive).

    Returns
    -------
    verdict, reason : str
        Flaws first as in :func:`compare`: if they decided, holds when ours is the flaw-free
        side and does not hold otherwise. Else holds if the interval (oriented so that positive
        favours ours) lies above ``-margin``, does not hold if it lies below, inconclusive if
        it straddles ``-margin``.
    """
    if c.by_flaws:
        if c.winner == "ours":
            return HOLDS, f"ahead: {c.basis}"
        return DOES_NOT_HOLD, f"behind: {c.basis}"
    _, low, high = c.oriented()
    if low >= -margin:
        return HOLDS, f"the interval lies above -{margin:.4g} (the margin)"
    if high < -margin:
        return DOES_NOT_HOLD, f"worse by more than the margin {margin:.4g}"
    return INCONCLUSIVE, f"the interval straddles -{margin:.4g} (the margin)"


def magnitude(c: Comparison, target: float) -> tuple[str, str]:
    """Verdict of "the effect is about ``target``".

    Parameters
    ----------
    c : Comparison
        Ours against the other; its statistic is the effect (a saving in %, a difference).
    target : float
        The paper's figure, in the units of the statistic.

    Returns
    -------
    verdict, reason : str
        Judged only when neither side has flaws (else the other's value is no like-for-like
        base: inconclusive). Holds if the interval covers ``target`` and excludes 0; does not
        hold if it excludes ``target``; inconclusive if it covers both.
    """
    if c.ours_flaws or c.other_flaws:
        return INCONCLUSIVE, "a side collides or fails, so its value is no like-for-like base"
    if c.low <= target <= c.high:
        if c.low > 0 or c.high < 0:
            return HOLDS, f"the interval covers {target:g} and excludes 0"
        return INCONCLUSIVE, f"the interval covers {target:g} and 0"
    side = "above" if c.low > target else "below"
    return DOES_NOT_HOLD, f"the interval lies {side} {target:g}"


def both_halves(first: tuple[str, str], second: tuple[str, str]) -> str:
    """Verdict of a claim with two halves.

    Parameters
    ----------
    first, second : (verdict, reason)
        Each half's verdict and reason (the caller states both reasons).

    Returns
    -------
    str
        Holds if both halves hold; does not hold if either does not; inconclusive if either is
        inconclusive; else (a half not testable) not testable here.
    """
    pair = (first[0], second[0])
    if pair == (HOLDS, HOLDS):
        return HOLDS
    for verdict in (DOES_NOT_HOLD, INCONCLUSIVE):
        if verdict in pair:
            return verdict
    return NOT_TESTABLE


def rate_interval(per_seed: Sequence[np.ndarray]) -> tuple[float, float, float]:
    """Mean and two-stage interval of a per-episode 0/1 indicator.

    Parameters
    ----------
    per_seed : sequence of 1-D arrays
        One array of per-episode indicators (a collision: 1) per training seed.

    Returns
    -------
    mean, low, high : float
        :func:`benchmark.statistics.hierarchical_bootstrap_ci` over training seeds, then
        episodes.
    """
    return hierarchical_bootstrap_ci([np.asarray(g, dtype=float) for g in per_seed])


def rate_at_most(rates: Mapping[str, tuple[float, float, float]],
                 bound: float) -> tuple[str, str]:
    """Verdict of "every controller's rate is at most ``bound``".

    Parameters
    ----------
    rates : mapping
        Controller -> (mean, low, high) of its rate (:func:`rate_interval`).
    bound : float
        The largest rate the claim allows (a fraction).

    Returns
    -------
    verdict, reason : str
        Holds if every interval lies at or below ``bound``, does not hold if some interval lies
        wholly above it, else inconclusive (not testable with no controller).
    """
    if not rates:
        return NOT_TESTABLE, "no controller"
    above = [n for n, (_, lo, _) in rates.items() if lo > bound]
    open_ = [n for n, (_, _, hi) in rates.items() if hi > bound]
    if above:
        return DOES_NOT_HOLD, f"{', '.join(above)} above {bound:.1%} (interval)"
    if open_:
        return INCONCLUSIVE, f"the interval of {', '.join(open_)} reaches above {bound:.1%}"
    return HOLDS, f"every interval at or below {bound:.1%}"


#: The paper's sentences behind each claim, as printed in ``bdc-marl-paper.tex`` (LaTeX ``\\%``
#: written ``%``); several sentences are joined by `` ... ``.
PAPER_QUOTES: dict[str, str] = {
    "energy": ("Our results show that BDC-MARL achieved the highest energy savings, improving by "
               "up to 5.8%, with an average velocity of 15.26 m/s and an inter-vehicle spacing of "
               "20.76 m."),
    "reward": "It achieved significantly higher rewards without compromising power consumption "
              "efficiency.",
    "collisions": "All algorithms effectively prioritized safety, with consistently low or zero "
                  "collisions.",
    "convergence": ("However, the BDC-MARL method stands out for its quick convergence and "
                    "stability, demonstrating its effectiveness in environments with limited "
                    "communication resources."),
    "qsgd": ("In the CACC scenario, by transmitting only three possible values for each gradient "
             "component, the system minimizes the amount of data exchanged between vehicles, "
             "preserving bandwidth for critical vehicular communications. ... Integrating QSGD "
             "into our communication protocol achieves stable performance and comparable energy "
             "savings across three information-sharing methods."),
    "size": ("Interestingly, a platoon size of 6 emerges as the most advantageous, exhibiting "
             "consistent IVS, moderate velocities, and the lowest variation in power consumption, "
             "indicative of an efficient balance between fuel efficiency and operational "
             "stability."),
    "sharing_reward": ("While BDC-MARL exhibits some mid-training variability, it ultimately "
                       "achieves the highest rewards, making it the most effective method for "
                       "maximizing training rewards."),
    "stability": ("The BDC-MARL approach quickly converges in terms of IVS and maintains a more "
                  "stable velocity and acceleration pattern, due to its efficient use of limited "
                  "bandwidth and information processing capabilities, preventing data overflow "
                  "and response lag."),
    "size_power": ("Larger platoons save fuel through reduced aerodynamic drag without "
                   "increasing power use proportionally."),
    "openacc": ("However, there are noticeable differences in the standard deviation of IVS, "
                "showing greater variability in the OpenACC."),
}

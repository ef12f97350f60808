"""The tests a reviewer asks of a within-subject rating study, on scipy.stats.

* Friedman's test across the models (participants are the blocks; scipy's statistic, corrected for
  ties) and Kendall's coefficient of concordance W = chi2 / (N (k - 1)) (Tomczak & Tomczak 2014,
  "The need to report effect size estimates revisited", Trends in Sport Sciences 21(1):19-25).
* Pairwise Wilcoxon signed-rank tests (scipy's default: zero differences dropped, exact p for
  small samples without ties, the normal approximation otherwise), p-values adjusted by Holm's
  step-down method (Holm 1979, Scand. J. Statist. 6:65-70) within each index.
* Medians and interquartile ranges (numpy's linear interpolation between order statistics).
* The order check: Friedman across trial positions; the carry-over check: the ratings less the
  participant's and the model's mean (an additive two-way fit), grouped by the model met just
  before, compared by Kruskal-Wallis.

Every function takes plain arrays; ``nan`` marks a missing rating.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from itertools import combinations

import numpy as np
from scipy import stats as ss


@dataclass(frozen=True)
class Friedman:
    n: int  # complete blocks (participants)
    k: int  # treatments
    chi2: float | None
    p: float | None
    w: float | None  # Kendall's W
    note: str = ""


def complete_rows(x: np.ndarray) -> np.ndarray:
    x = np.asarray(x, dtype=float)
    return x[np.all(np.isfinite(x), axis=1)]


def friedman(x) -> Friedman:
    """Friedman's test on ``x`` (blocks x treatments); blocks with a missing value are left out."""
    x = complete_rows(x)
    n, k = x.shape
    if k < 3:
        return Friedman(n, k, None, None, None, "Friedman's test needs 3 or more models (see the Wilcoxon test)")
    if n < 2:
        return Friedman(n, k, None, None, None, f"{n} complete participant(s): too few")
    if np.all(np.ptp(x, axis=1) == 0):
        return Friedman(n, k, 0.0, 1.0, 0.0, "every participant gave every model the same rating")
    chi2, p = ss.friedmanchisquare(*x.T)
    return Friedman(n, k, float(chi2), float(p), float(chi2) / (n * (k - 1)))


def holm(p) -> np.ndarray:
    """Holm's step-down adjusted p-values (same order as ``p``; nan stays nan)."""
    p = np.asarray(p, dtype=float)
    out = np.full(p.shape, np.nan)
    ok = np.flatnonzero(np.isfinite(p))
    m = ok.size
    order = ok[np.argsort(p[ok], kind="stable")]
    running = 0.0
    for i, j in enumerate(order):
        running = max(running, min(1.0, (m - i) * p[j]))
        out[j] = running
    return out


@dataclass(frozen=True)
class Pair:
    a: int
    b: int
    n: int  # participants with both ratings
    nonzero: int  # of them, with a difference
    statistic: float | None
    p: float | None
    median_difference: float | None  # median of a - b


def wilcoxon_pairs(x) -> list[Pair]:
    """Wilcoxon signed-rank test of every pair of columns of ``x`` (participants x models)."""
    x = np.asarray(x, dtype=float)
    out = []
    for a, b in combinations(range(x.shape[1]), 2):
        both = np.isfinite(x[:, a]) & np.isfinite(x[:, b])
        d = x[both, a] - x[both, b]
        n, nz = int(both.sum()), int(np.count_nonzero(d))
        if nz == 0:
            out.append(Pair(a, b, n, 0, None if n == 0 else 0.0, None if n == 0 else 1.0,
                            None if n == 0 else 0.0))
            continue
        res = ss.wilcoxon(x[both, a], x[both, b])
        out.append(Pair(a, b, n, nz, float(res.statistic), float(res.pvalue), float(np.median(d))))
    return out


@dataclass(frozen=True)
class Describe:
    n: int
    median: float | None
    q1: float | None
    q3: float | None
    mean: float | None

    @property
    def iqr(self) -> float | None:
        return None if self.q1 is None else self.q3 - self.q1


def describe(v) -> Describe:
    v = np.asarray(v, dtype=float)
    v = v[np.isfinite(v)]
    if v.size == 0:
        return Describe(0, None, None, None, None)
    q1, med, q3 = np.percentile(v, [25, 50, 75])
    return Describe(int(v.size), float(med), float(q1), float(q3), float(v.mean()))


@dataclass(frozen=True)
class CarryOver:
    groups: int  # predecessor models with residuals
    n: int  # ratings compared
    h: float | None
    p: float | None
    mean_residual: dict  # predecessor model index -> mean residual


def carry_over(ratings: dict, order: dict) -> CarryOver:
    """``ratings[(p, t)]``: a rating; ``order[p]``: participant ``p``'s sequence of model indices.
    Residual of each rating from the additive fit (participant mean + model mean - grand mean,
    over all the ratings given), grouped by the model of the trial before it."""
    if not ratings:
        return CarryOver(0, 0, None, None, {})
    vals = np.array(list(ratings.values()), dtype=float)
    grand = float(vals.mean())
    by_p: dict = {}
    by_m: dict = {}
    for (p, t), v in ratings.items():
        by_p.setdefault(p, []).append(v)
        by_m.setdefault(order[p][t - 1], []).append(v)
    mp = {p: float(np.mean(v)) for p, v in by_p.items()}
    mm = {m: float(np.mean(v)) for m, v in by_m.items()}
    groups: dict = {}
    for (p, t), v in ratings.items():
        if t == 1:
            continue
        m = order[p][t - 1]
        groups.setdefault(order[p][t - 2], []).append(v - mp[p] - mm[m] + grand)
    mean_res = {g: float(np.mean(r)) for g, r in sorted(groups.items())}
    n = sum(len(r) for r in groups.values())
    usable = [np.asarray(r) for r in groups.values() if len(r)]
    if len(usable) < 2:
        return CarryOver(len(usable), n, None, None, mean_res)
    allv = np.concatenate(usable)
    if np.ptp(allv) < 1e-12:
        return CarryOver(len(usable), n, 0.0, 1.0, mean_res)
    h, p = ss.kruskal(*usable)
    return CarryOver(len(usable), n, float(h), float(p) if math.isfinite(p) else None, mean_res)

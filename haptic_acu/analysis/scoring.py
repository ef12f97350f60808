"""Multi-index comprehensive weighted scoring of the paper's user study (section 4.2).

Raters score each acupuncture system on ``m`` indices (the paper's seven, :data:`INDICES`) from 0
to 10. A rater's comprehensive score is a weighted sum of their index scores (eq. 14) whose weights
mix a subjective part, agreed by experts in Delphi rounds, with an objective part, from how much
the raters disagree on each index (the mean square deviation method, eq. 10-12):

* eq. 10  ``E_j = mean_i x_ij``
* eq. 11  ``sigma_j = sqrt(mean_i (x_ij - E_j)^2)``  (population standard deviation)
* eq. 12  ``beta_j = sigma_j / sum_k sigma_k``
* eq. 13  ``omega_j = mu * alpha_j + (1 - mu) * beta_j``,  ``0 < mu < 1`` (paper: 0.4)
* eq. 14  ``f_i = sum_j omega_j x_ij``

The objective weights are computed per system (over that system's raters), so each system gets
its own combined weights (the paper's Table 4); the subjective weights are shared (Table 3).

Everything here is pure numpy on dimensionless scores and weights; bad numbers raise
:class:`ValueError` (the ``score`` command turns those into one-line user errors naming the file).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

#: The paper's seven evaluation indices, in its order (Table 3 columns).
INDICES = (
    "soft_tissue_material",
    "force_feedback",
    "acupuncture_effect",
    "training_environment",
    "real_time",
    "training_effect",
    "system_stability",
)

#: Table 3: the Delphi subjective weights alpha_j, in :data:`INDICES` order.
PAPER_SUBJECTIVE_WEIGHTS = (0.09, 0.17, 0.24, 0.13, 0.10, 0.21, 0.06)

#: The paper's preference coefficient mu of eq. 13.
PAPER_MU = 0.4

#: The paper's Delphi bound on each index's standard deviation of expert weights.
PAPER_DELPHI_BOUND = 0.1

#: Scores are on a 0-10 scale.
SCORE_MIN, SCORE_MAX = 0.0, 10.0

#: Tolerance on "a weight vector sums to 1".
WEIGHT_SUM_TOL = 1e-6

# A standard deviation within this of the Delphi bound counts as "not exceeding" it, so that a
# spread exactly at the bound is not pushed over by floating-point rounding.
_BOUND_SLACK = 1e-12


def _as_matrix(x) -> np.ndarray:
    a = np.asarray(x, dtype=float)
    if a.ndim != 2 or a.shape[0] < 1 or a.shape[1] < 1:
        raise ValueError(f"expected a 2-D (rows x indices) array, got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError("non-finite value")
    return a


def check_weights(w, what: str = "weights") -> np.ndarray:
    """Return ``w`` as a float vector after checking it is finite, non-negative and sums to 1
    within :data:`WEIGHT_SUM_TOL`. It is not rescaled: a wrong sum is an error, not a typo to fix."""
    a = np.asarray(w, dtype=float)
    if a.ndim != 1 or a.size < 1:
        raise ValueError(f"{what}: expected a 1-D vector, got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{what}: non-finite weight")
    if np.any(a < 0):
        raise ValueError(f"{what}: negative weight")
    s = math.fsum(a.tolist())
    if abs(s - 1.0) > WEIGHT_SUM_TOL:
        raise ValueError(f"{what}: weights sum to {s:.9g}, not 1 (tolerance {WEIGHT_SUM_TOL:g})")
    return a


@dataclass(frozen=True)
class ObjectiveWeights:
    """The mean square deviation method's results for one system (eq. 10-12), per index."""

    mean: np.ndarray  # E_j, eq. 10 (score points)
    sigma: np.ndarray  # sigma_j, eq. 11 (score points, population standard deviation)
    beta: np.ndarray  # beta_j, eq. 12 (dimensionless, sums to 1)


def objective_weights(x) -> ObjectiveWeights:
    """Eq. 10-12 on one system's score matrix ``x`` (raters x indices).

    sigma_j is the population standard deviation (divide by n). An index every rater scored the
    same has sigma_j = 0 exactly (hence beta_j = 0). If every index is constant the weights are
    undefined (0/0): :class:`ValueError`.
    """
    a = _as_matrix(x)
    n = a.shape[0]
    mean = a.sum(axis=0) / n  # eq. 10
    sigma = np.sqrt(((a - mean) ** 2).sum(axis=0) / n)  # eq. 11
    # A constant column's mean can differ from its values in the last bit; its sigma is 0.
    sigma[np.ptp(a, axis=0) == 0] = 0.0
    total = sigma.sum()
    if not total > 0:
        raise ValueError("every index has the same score from every rater, so the mean square "
                         "deviation weights are 0/0")
    return ObjectiveWeights(mean=mean, sigma=sigma, beta=sigma / total)  # eq. 12


def combined_weights(alpha, beta, mu: float = PAPER_MU) -> np.ndarray:
    """Eq. 13: omega_j = mu * alpha_j + (1 - mu) * beta_j, with 0 < mu < 1 (the larger mu, the
    more the subjective weights count). If alpha and beta each sum to 1, so does omega."""
    mu = float(mu)
    if not 0.0 < mu < 1.0:
        raise ValueError(f"mu must satisfy 0 < mu < 1, got {mu}")
    a = np.asarray(alpha, dtype=float)
    b = np.asarray(beta, dtype=float)
    if a.shape != b.shape:
        raise ValueError(f"alpha has shape {a.shape} but beta has {b.shape}")
    return mu * a + (1.0 - mu) * b


def final_scores(x, omega) -> np.ndarray:
    """Eq. 14: f_i = sum_j omega_j x_ij, one comprehensive score per rater (row of ``x``)."""
    a = _as_matrix(x)
    w = np.asarray(omega, dtype=float)
    if w.shape != (a.shape[1],):
        raise ValueError(f"{a.shape[1]} indices but {w.size} weights")
    return a @ w


@dataclass(frozen=True)
class DelphiRound:
    """One Delphi round's statistics over its experts' weight vectors."""

    number: int
    n_experts: int
    mean: np.ndarray  # mean weight of each index
    std: np.ndarray  # standard deviation of each index's weights
    exceeding: tuple[int, ...]  # indices (column numbers) whose std exceeds the bound


@dataclass(frozen=True)
class DelphiResult:
    rounds: tuple[DelphiRound, ...]
    bound: float
    converged: bool  # the last round has no index above the bound
    converged_round: int | None  # first round with none above the bound (None if never)
    weights: np.ndarray  # subjective weights alpha: that round's mean, else the last round's


def delphi_round(number: int, weights, bound: float = PAPER_DELPHI_BOUND, ddof: int = 0) -> DelphiRound:
    """Step 3-4 of the Delphi method for one round: mean and standard deviation of each index's
    weights over the experts (rows), and which indices' standard deviation exceeds ``bound``.
    ``ddof=0`` (default) is the population standard deviation, as in eq. 11; a std equal to the
    bound does not exceed it."""
    a = _as_matrix(weights)
    n = a.shape[0]
    if n - ddof < 1:
        raise ValueError(f"round {number}: {n} expert(s) is too few for a standard deviation")
    mean = a.sum(axis=0) / n
    std = np.sqrt(((a - mean) ** 2).sum(axis=0) / (n - ddof))
    std[np.ptp(a, axis=0) == 0] = 0.0
    exceeding = tuple(int(j) for j in np.flatnonzero(std > bound + _BOUND_SLACK))
    return DelphiRound(number=number, n_experts=n, mean=mean, std=std, exceeding=exceeding)


def delphi(rounds, bound: float = PAPER_DELPHI_BOUND, ddof: int = 0) -> DelphiResult:
    """Step 3-5 of the Delphi method over successive rounds (a sequence of experts x indices
    weight matrices, round 1 first). The subjective weights are the mean of the first round in
    which no index's standard deviation exceeds ``bound``; rounds after it are still summarised
    but do not change the result. If no round reaches agreement, ``converged`` is False and the
    weights are the last round's mean (the caller decides whether to accept that)."""
    bound = float(bound)
    if not (math.isfinite(bound) and bound > 0):
        raise ValueError(f"the Delphi bound must be a positive number, got {bound}")
    stats = tuple(delphi_round(k + 1, r, bound, ddof) for k, r in enumerate(rounds))
    if not stats:
        raise ValueError("no Delphi rounds")
    width = {s.mean.size for s in stats}
    if len(width) != 1:
        raise ValueError("Delphi rounds have different numbers of indices")
    first_ok = next((s for s in stats if not s.exceeding), None)
    chosen = first_ok if first_ok is not None else stats[-1]
    return DelphiResult(
        rounds=stats,
        bound=bound,
        converged=first_ok is not None,
        converged_round=None if first_ok is None else first_ok.number,
        weights=chosen.mean.copy(),
    )


@dataclass(frozen=True)
class SystemScore:
    """All of one system's scoring: objective (eq. 10-12), combined (eq. 13) weights and scores."""

    name: str
    raters: tuple[str, ...]
    objective: ObjectiveWeights
    omega: np.ndarray  # eq. 13
    scores: np.ndarray  # eq. 14, one per rater

    @property
    def mean_score(self) -> float:
        return float(self.scores.mean())


def score_system(name: str, raters, x, alpha, mu: float = PAPER_MU) -> SystemScore:
    """Score one system: ``x`` is its raters x indices matrix (0-10), ``alpha`` the subjective
    weights. Needs at least two raters (one rater has no spread to weigh by)."""
    a = _as_matrix(x)
    raters = tuple(str(r) for r in raters)
    if len(raters) != a.shape[0]:
        raise ValueError(f"{len(raters)} rater names for {a.shape[0]} rows")
    if a.shape[0] < 2:
        raise ValueError(f"system {name!r} has {a.shape[0]} rater; at least 2 are needed")
    if np.any((a < SCORE_MIN) | (a > SCORE_MAX)):
        raise ValueError(f"scores must lie in [{SCORE_MIN:g}, {SCORE_MAX:g}]")
    alpha = check_weights(alpha, "subjective weights")
    if alpha.size != a.shape[1]:
        raise ValueError(f"{alpha.size} subjective weights for {a.shape[1]} indices")
    obj = objective_weights(a)
    omega = combined_weights(alpha, obj.beta, mu)
    return SystemScore(name=name, raters=raters, objective=obj, omega=omega, scores=final_scores(a, omega))

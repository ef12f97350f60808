"""What a setting will cost, checked before the work starts (docs/outputs.md, "Cost budgets").

Some values are legal one at a time and absurd together: a force net of 40 rings solved to the
smallest static tolerance, a degree-40 body fitted to 200,000 samples, a calibration curve replayed
tick by tick at a micrometre a second. Each estimate here is the work's own arithmetic (particles x
sweeps x rows; samples x coefficients; ticks) with constants measured on this project's kernels
(docs/outputs.md gives the measurements); a setting whose estimate passes the budget is refused in
one line naming the keys and the cost, before anything is solved or allocated.

Budgets: :data:`TIME_BUDGET_S` of computing and :data:`MEMORY_BUDGET_BYTES` of memory for one
step, unless the environment sets ``HAPTIC_ACU_TIME_BUDGET_S`` / ``HAPTIC_ACU_MEMORY_BUDGET_GB``
(to let a long job run on purpose).
"""
from __future__ import annotations

import math
import os

from .errors import UserError

TIME_BUDGET_S = 300.0
MEMORY_BUDGET_BYTES = 2 << 30

# the force net's table build (haptic_acu.tissue.netresponse.build), measured on the project's
# 2-core machine: 9 columns of rows, each row a few Gauss-Seidel sweeps over every particle
NET_COLUMNS = 9
NET_S_PER_PARTICLE_SWEEP = 150e-9  # 92-195 ns measured (w = 6-16), two columns at a time
NET_ROWS_TYPICAL = 3100  # rows to the default skin's break (w >= 6); the cap is 20000
NET_THREADS = 2


def time_budget_s() -> float:
    v = os.environ.get("HAPTIC_ACU_TIME_BUDGET_S")
    try:
        return float(v) if v else TIME_BUDGET_S
    except ValueError:
        raise UserError(f"HAPTIC_ACU_TIME_BUDGET_S={v!r}: not a number of seconds") from None


def memory_budget_bytes() -> float:
    v = os.environ.get("HAPTIC_ACU_MEMORY_BUDGET_GB")
    try:
        return float(v) * (1 << 30) if v else MEMORY_BUDGET_BYTES
    except ValueError:
        raise UserError(f"HAPTIC_ACU_MEMORY_BUDGET_GB={v!r}: not a number of gigabytes") from None


def _human_s(s: float) -> str:
    if s < 120:
        return f"{s:.0f} s"
    if s < 7200:
        return f"{s / 60:.0f} minutes"
    return f"{s / 3600:.1f} hours"


def _human_b(b: float) -> str:
    return f"{b / (1 << 30):.1f} GB" if b >= 1 << 30 else f"{b / (1 << 20):.0f} MB"


def net_sweeps_per_row(rings: int, tol_m: float) -> float:
    """Gauss-Seidel sweeps a row of the net's table takes, summed over its 9 columns' share: fitted to
    the measured 3.3-3.9 (tolerance 1e-10 m) and 10-40 (1e-12 m) for w = 3-16; it grows with the rings
    and with the tolerance's tightness, and is an over-estimate at each measured point."""
    return 3.0 + 0.12 * rings * (1e-10 / max(tol_m, 1e-300)) ** 0.69


def net_cost(rings: int, tol_m: float) -> tuple[float, float, int]:
    """(seconds, bytes, sweeps) the static response table of a ``rings``-ring net solved to ``tol_m``
    is estimated to take."""
    n = 3 * rings * (rings - 1) + 1
    sweeps = NET_COLUMNS * NET_ROWS_TYPICAL * net_sweeps_per_row(rings, tol_m)
    seconds = sweeps * n * NET_S_PER_PARTICLE_SWEEP / NET_THREADS
    memory = NET_ROWS_TYPICAL * n * 3 * 8.0  # the displacement field of every row
    return seconds, memory, int(sweeps)


def check_net(layer: str, rings: int, tol_um: float, where: str) -> None:
    """Refuse (one line) a layer whose net table would pass the budget."""
    s, b, sweeps = net_cost(rings, tol_um * 1e-6)
    if s > time_budget_s():
        raise UserError(f"{where}: {layer}.rings={rings} with solver.static_tolerance_um={tol_um:g} needs "
                        f"about {sweeps:,} sweeps of {3 * rings * (rings - 1) + 1:,} particles, "
                        f"about {_human_s(s)} to tabulate (budget {_human_s(time_budget_s())}); raise the "
                        "tolerance or lower the rings")
    if b > memory_budget_bytes():
        raise UserError(f"{where}: {layer}.rings={rings} needs about {_human_b(b)} for its table (budget "
                        f"{_human_b(memory_budget_bytes())}); lower the rings")


def sh_fit_cost(lmax: int, samples: int) -> tuple[float, float]:
    """(seconds, bytes) of the body's four least-squares fits: a samples x (lmax+1)^2 basis, its Gram
    matrix (samples x coefficients^2 multiply-adds: lmax 40 with 200,000 samples took 66 s and 2.9 GB
    here, about 3.4e10 a second; counted at half that) and a residual copy."""
    k = (lmax + 1) ** 2
    memory = 8.0 * samples * k * 3
    seconds = 4.0 * samples * k * k / 1.7e10
    return seconds, memory


def check_sh_fit(lmax: int, samples: int, where: str, keys: bool = True) -> None:
    """Refuse a fit of ``samples`` points at degree ``lmax`` past the budget; ``keys``: name the config
    keys (else ``where`` names the arguments)."""
    s, b = sh_fit_cost(lmax, samples) if keys else (sh_fit_cost(lmax, samples)[0] / 4, sh_fit_cost(lmax, samples)[1])
    if not keys and (b > memory_budget_bytes() or s > time_budget_s()):
        raise UserError(f"{where} need about {_human_b(b)} and {_human_s(s)} to fit (budget "
                        f"{_human_b(memory_budget_bytes())}, {_human_s(time_budget_s())}); lower --lmax")
    if b > memory_budget_bytes() or s > time_budget_s():
        raise UserError(f"{where}: body.lmax={lmax} with body.fit_samples={samples:,} needs about "
                        f"{_human_b(b)} and {_human_s(s)} to fit the body (budget {_human_b(memory_budget_bytes())}, "
                        f"{_human_s(time_budget_s())}); lower body.fit_samples (2*(lmax+1)^2 = "
                        f"{2 * (lmax + 1) ** 2:,} is the least) or body.lmax")


def check_ticks(what: str, ticks: float, s_per_tick: float, bytes_per_tick: float) -> None:
    """Refuse a tick-by-tick computation of ``ticks`` ticks that would pass the budget; ``what`` names
    the arguments (e.g. "--speed-mm-s 1e-06 over the curve's 12 mm")."""
    s, b = ticks * s_per_tick, ticks * bytes_per_tick
    if not math.isfinite(ticks) or s > time_budget_s() or b > memory_budget_bytes():
        raise UserError(f"{what} is {ticks:,.0f} servo ticks, about {_human_s(s)} and {_human_b(b)} to "
                        f"compute (budget {_human_s(time_budget_s())}, {_human_b(memory_budget_bytes())})")

"""The study's design: Williams Latin squares, the participants' trial order and the system codes.

A Williams square (Williams 1949, "Experimental designs balanced for the estimation of residual
effects of treatments", Aust. J. Sci. Res. A 2:149-168) orders ``n`` treatments so that every
treatment appears once in every position (a Latin square) and every treatment follows every other
one equally often (balanced for first-order carry-over). For even ``n`` one square of ``n`` rows
does it; for odd ``n`` no single square can, and the square plus its mirror image (each row
reversed), ``2 n`` rows, does (each ordered pair then follows twice).

Construction (the standard one): the first row is ``0, 1, n-1, 2, n-2, 3, ...``; row ``i`` adds
``i`` to every entry (mod ``n``).

Everything here is pure: integers in, integers out, a ``numpy.random.Generator`` for the random
parts (which model is which symbol, which participant gets which row, the system codes).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

MIN_MODELS, MAX_MODELS = 2, 8


def williams_rows(n: int) -> list[list[int]]:
    """The rows of the Williams design for ``n`` treatments (0..n-1): ``n`` rows for even ``n``,
    ``2 n`` (the square and its mirror) for odd ``n``."""
    if not MIN_MODELS <= n <= MAX_MODELS:
        raise ValueError(f"a Williams design here takes {MIN_MODELS}-{MAX_MODELS} treatments, got {n}")
    first = [0]
    lo, hi = 1, n - 1
    for k in range(1, n):
        if k % 2:
            first.append(lo)
            lo += 1
        else:
            first.append(hi)
            hi -= 1
    square = [[(v + i) % n for v in first] for i in range(n)]
    if n % 2 == 0:
        return square
    return square + [row[::-1] for row in square]


def square_size(n: int) -> int:
    """Rows of one complete Williams design for ``n`` treatments."""
    return n if n % 2 == 0 else 2 * n


@dataclass(frozen=True)
class Schedule:
    """Who does what when: ``order[p]`` is participant ``p``'s sequence of model indices (its
    length ``n_models * trials_per_model``), ``rows[p]`` the design rows it was built from."""

    n_models: int
    order: tuple[tuple[int, ...], ...]
    rows: tuple[tuple[int, ...], ...]
    design: tuple[tuple[int, ...], ...]  # the Williams rows, in model indices, as assigned

    @property
    def block(self) -> int:
        return len(self.design)


def schedule(n_models: int, n_participants: int, trials_per_model: int, rng: np.random.Generator) -> Schedule:
    """Participants' orders from a Williams design of ``n_models``.

    The models are assigned to the design's symbols at random (a random relabelling keeps the
    design's balance). Participants take the design's rows in blocks of one complete design, each
    block in its own random order, so every complete block of participants is balanced. With
    ``trials_per_model`` K > 1 a participant's K passes are K consecutive rows (cyclically) after
    its own: each pass is balanced, the pairs across passes are not."""
    if n_participants < 1:
        raise ValueError("at least one participant")
    if trials_per_model < 1:
        raise ValueError("at least one trial per model")
    base = williams_rows(n_models)
    relabel = rng.permutation(n_models)
    design = [[int(relabel[v]) for v in row] for row in base]
    s = len(design)
    order, rows = [], []
    perm = None
    for p in range(n_participants):
        if p % s == 0:
            perm = rng.permutation(s)
        first = int(perm[p % s])
        mine = [(first + k) % s for k in range(trials_per_model)]
        rows.append(tuple(mine))
        order.append(tuple(v for r in mine for v in design[r]))
    return Schedule(n_models, tuple(order), tuple(rows), tuple(tuple(r) for r in design))


def system_codes(n_models: int, n_participants: int, per_participant: bool,
                 rng: np.random.Generator) -> list[list[int]]:
    """``codes[p][m]``: the system number (1..n) participant ``p`` sees for model ``m``. One random
    numbering for everyone, or (``per_participant``) a fresh one for each participant."""
    shared = [int(c) + 1 for c in rng.permutation(n_models)]
    out = []
    for _ in range(n_participants):
        out.append([int(c) + 1 for c in rng.permutation(n_models)] if per_participant else list(shared))
    return out


def neighbour_pair_counts(orders, n: int) -> np.ndarray:
    """``counts[a, b]``: how often model ``b`` directly follows model ``a`` within the sequences."""
    c = np.zeros((n, n), dtype=int)
    for seq in orders:
        for a, b in zip(seq[:-1], seq[1:]):
            c[a, b] += 1
    return c


def position_counts(orders, n: int) -> np.ndarray:
    """``counts[m, k]``: how often model ``m`` is at position ``k`` of the sequences."""
    length = len(orders[0])
    c = np.zeros((n, length), dtype=int)
    for seq in orders:
        for k, m in enumerate(seq):
            c[m, k] += 1
    return c

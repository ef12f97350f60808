"""The compiled CSV formatter against Python's own formatting."""
import math

import numpy as np

from haptic_acu.base.csvfmt import RowFormatter


def _near_tie(x: float, d: int) -> bool:
    s = abs(x) * 10 ** d
    return abs((s - math.floor(s)) - 0.5) < 1e-6


def test_fixed_decimals_match_python_format():
    rng = np.random.default_rng(1)
    vals = np.concatenate([rng.normal(0, 1, 3000), rng.normal(0, 1e3, 3000), rng.uniform(-1e-4, 1e-4, 1000),
                           [0.0, -0.0, 1.0, -1.0, 123456.789, -0.00004, 0.00005, 9.99999999]])
    for d in (0, 1, 4, 6):
        fmt = RowFormatter([("fixed", d)])
        got = fmt.format(vals[:, None]).decode().splitlines()
        for x, g in zip(vals, got):
            ref = f"{x:.{d}f}"
            if ref.startswith("-") and float(ref) == 0.0:
                ref = ref[1:]  # we never write negative zero
            if g != ref:
                assert _near_tie(x, d), (x, d, g, ref)


def test_categories_empty_cells_and_nan():
    fmt = RowFormatter([("category", ("outside", "skin")), ("fixed", 2), ("category", ("a", "bb"))])
    rows = np.array([[0, 1.234, 1], [1, np.nan, np.nan], [1, -0.001, 0]])
    assert fmt.format(rows).decode() == "outside,1.23,bb\nskin,nan,\nskin,0.00,a\n"


def test_gather_equals_format_of_the_built_columns():
    """format_gather (columns taken, scaled and offset inside the compiled pass) writes the bytes
    format writes for the same columns built with numpy; negative category codes are empty cells."""
    rng = np.random.default_rng(3)
    rows = rng.normal(0, 1, (500, 6))
    rows[:, 2] = rng.integers(-1, 3, 500)  # a category code column, -1: none
    rows[::7, 1] = np.nan
    extra = rng.normal(0, 1e-3, (500, 2))
    cols = [("fixed", 4), ("category", ("a", "bb", "ccc", "d")), ("category", ("x", "y", "z")), ("fixed", 6),
            ("fixed", 0)]
    fmt = RowFormatter(cols)
    src, scale, offset = [1, 2, 2, 6, 0], [1e3, 1.0, 1.0, 1e3, 1.0], [0.0, 1.0, 0.0, 0.0, 0.0]
    punct = rows[:, 2].copy()
    punct[punct < 0] = np.nan
    built = np.column_stack([rows[:, 1] * 1e3, rows[:, 2] + 1, punct, extra[:, 0] * 1e3, rows[:, 0]])
    assert fmt.format_gather(rows, extra, src, scale, offset) == fmt.format(built)
    assert b",," in fmt.format_gather(rows, extra, src, scale, offset)  # some -1 codes: empty cells

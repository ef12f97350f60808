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


def _rule(v: float, d: int) -> str | None:
    """The formatter's rule in Python's exact integers: floor(|v| * 10.0**d + 0.5) (the float sum,
    floored exactly) with a point before its last d digits, '-' unless that integer is 0, "nan" for a
    value that is not finite. None where the integer does not fit an int64 (not compared)."""
    v = float(v)  # Python's float: the same IEEE arithmetic, and an overflow to inf without a warning
    if not math.isfinite(v):
        return "nan"
    x = abs(v) * 10.0 ** d + 0.5
    if not x < 2.0 ** 63:
        return None
    iv = math.floor(x)
    if iv >= 2 ** 63:
        return None
    s = str(iv).rjust(d + 1, "0")
    if d:
        s = s[:-d] + "." + s[-d:]
    return ("-" if iv != 0 and v < 0 else "") + s


def _edge_values(rng) -> np.ndarray:
    parts = [rng.normal(0, 1, 4000),
             np.sign(rng.normal(size=6000)) * 10 ** rng.uniform(-12, 19, 6000)]  # every magnitude
    for d in (0, 1, 4, 5, 6, 9):
        k = rng.integers(-10 ** 7, 10 ** 7, 1500)
        ties = (k + 0.5) / 10.0 ** d  # halves at d decimals (exact or nearest), and their neighbours
        parts += [ties, np.nextafter(ties, np.inf), np.nextafter(ties, -np.inf),
                  rng.integers(-2 ** 53, 2 ** 53, 500) / 10.0 ** d]  # up to the digits a float holds
    edge = []
    for d in range(17):  # where |v| * 10**d + 0.5 crosses 2**53 (the two-digit path's bound)
        t = 2.0 ** 53 / 10.0 ** d
        edge += [t, -t, np.nextafter(t, 0.0), np.nextafter(t, np.inf), (2.0 ** 53 - 0.5) / 10.0 ** d,
                 (2.0 ** 53 - 1.5) / 10.0 ** d]
    edge += [9.9999995, 0.99999995, 99.9999995, -9.9999995, 0.0, -0.0, 5e-324, -5e-324, 1e-300, 0.00005,
             -0.00005, 0.5, -0.5, 1.5, 2.5, 9.2e18, 9.3e18, 1e300, -1e300, np.inf, -np.inf, np.nan,
             1.7976931348623157e308]
    return np.concatenate(parts + [np.array(edge)])


def test_fixed_cells_follow_the_rounding_rule_bit_for_bit():
    """Every fixed cell is the rule's string (:func:`_rule`), for random values of every magnitude,
    halves and their neighbouring floats, values near the two-digit path's 2**53 bound, tiny, huge,
    signed zero and non-finite values, at 0 to 16 decimals; a value past the int64 range writes what
    the one-digit-a-time path writes (the same cell in every column, whatever the others hold)."""
    vals = _edge_values(np.random.default_rng(7))
    for d in (0, 1, 2, 4, 5, 6, 9, 12, 16):
        fmt = RowFormatter([("fixed", d), ("category", ("a", "bb")), ("fixed", d)])
        rows = np.column_stack([vals, np.zeros(len(vals)), vals[::-1]])
        got = fmt.format(rows).decode().splitlines()
        assert len(got) == len(vals)
        for x, y, line in zip(vals, vals[::-1], got):
            a, cat, b = line.split(",")
            assert cat == "a"
            for v, cell in ((x, a), (y, b)):
                want = _rule(v, d)
                if want is not None:
                    assert cell == want, (repr(v), d, cell, want)
        single = fmt.format(np.array([[1e300, 1.0, 1e300]])).decode()
        assert single.split(",")[0] == single.strip().split(",")[2]


def test_write_gather_writes_format_gathers_bytes_through_its_kept_buffer():
    """write_gather: the bytes format_gather returns, block after block of changing sizes (its
    buffer kept and grown, never a stale byte from a longer block before)."""
    import io

    rng = np.random.default_rng(11)
    fmt = RowFormatter([("fixed", 4), ("category", ("a", "bb")), ("fixed", 0)])
    f = io.BytesIO()
    want = b""
    for k in (5, 300, 2, 1000, 0, 7):
        rows = np.column_stack([rng.normal(0, 1e3, k), rng.integers(0, 2, k), rng.normal(0, 1e6, k)])
        extra = np.zeros((k, 0))
        n = fmt.write_gather(f, rows, extra, [0, 1, 2], [1.0, 1.0, 1.0], [0.0, 0.0, 0.0])
        block = fmt.format_gather(rows, extra, [0, 1, 2], [1.0, 1.0, 1.0], [0.0, 0.0, 0.0])
        assert n == len(block) and block.count(b"\n") == k
        want += block
    assert f.getvalue() == want


# Property tests: whole blocks against an independent Python formatting, line by line.

from decimal import ROUND_HALF_UP, Decimal  # noqa: E402

from hypothesis import example, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

_FLOATS = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True),  # every magnitude, subnormals, signed zeros
    st.floats(-1e6, 1e6),
    st.integers(-10 ** 6, 10 ** 6).flatmap(lambda k: st.sampled_from([float(k), k / 1e2, k / 1e4, k / 1e6])),
    st.integers(-10 ** 9, 10 ** 9).map(lambda k: k / 2.0 ** 11),  # halves, quarters...: exact ties
    st.integers(-10 ** 12, 10 ** 12).flatmap(lambda k: st.sampled_from([k / 1e4, k / 1e5, (k + 0.5) / 1e5])),
    st.sampled_from([0.0, -0.0, 5e-324, -0.00004, 0.00005, -0.000005, 9.9999995, 1e16, 9.999999999999998e15,
                     2.0 ** 53, 1e300, float("nan"), float("inf"), -float("inf")]),
)
_NAMES = st.lists(st.text("abcxyz_", min_size=0, max_size=19), min_size=1, max_size=5)


def _cell(kind, spec, v) -> str:
    """A cell by the formatter's rules in plain Python (:func:`_rule`'s numbers; a category's name,
    empty for a negative or non-finite code)."""
    if kind == "fixed":
        return _rule(v, spec)
    if not math.isfinite(v) or v < 0:
        return ""
    return spec[int(v)]


@st.composite
def _blocks(draw):
    """Columns of random kinds, and rows whose cells often repeat the row above's (the copied runs:
    single cells, neighbours, whole lines) or flip between 0.0 and -0.0."""
    cols = draw(st.lists(st.one_of(st.tuples(st.just("fixed"), st.integers(0, 16)),
                                   st.tuples(st.just("category"), _NAMES)), min_size=1, max_size=7))
    n = draw(st.integers(1, 12))
    rows = []
    for i in range(n):
        row = []
        for c, (kind, spec) in enumerate(cols):
            if i > 0 and draw(st.integers(0, 2)) == 0:
                v = rows[-1][c]  # the value above
                v = -v if v == 0.0 and draw(st.booleans()) else v
            elif kind == "category":
                v = draw(st.one_of(st.integers(-1, len(spec) - 1).map(float), st.just(float("nan"))))
            else:
                v = draw(_FLOATS)
            row.append(v)
        rows.append(row)
    return cols, np.array(rows, dtype=np.float64).reshape(n, len(cols))


@settings(max_examples=400, deadline=None)
@given(_blocks())
def test_blocks_are_the_python_formatting_of_each_cell(block):
    """Every line of a random block (cells repeated from the row above or not, any magnitude, ties,
    signed zeros, NaN and infinities, names of 0 to 19 bytes across the 8-byte words) is its cells
    formatted one by one in Python; a block cut anywhere gives the same bytes part by part."""
    cols, rows = block
    fmt = RowFormatter(cols)
    want = []
    for row in rows:
        cells = [_cell(kind, spec, v) for (kind, spec), v in zip(cols, row)]
        if None in cells:
            return  # an integer past int64 (the one-digit path's own range): not compared
        want.append(",".join(cells) + "\n")
    got = fmt.format(rows).decode("ascii")
    assert got == "".join(want)
    cut = len(rows) // 2
    assert fmt.format(rows[:cut]).decode() + fmt.format(rows[cut:]).decode() == got if cut else True


@settings(max_examples=300, deadline=None)
@given(st.one_of(st.floats(-1e11, 1e11), st.integers(-10 ** 6, 10 ** 6).map(lambda k: k / 1e4)), st.integers(0, 7))
@example(0.125, 2)
@example(-0.125, 2)
@example(2.5, 0)
@example(-0.00049999999999999996, 3)
@example(99999999.99999999, 7)
def test_fixed_cells_are_the_decimal_rounding_half_away_from_zero(v, d):
    """Away from a tie (where the rule rounds the float product v * 10**d, not v itself), a fixed
    cell is v's exact decimal value rounded half away from zero, without a negative zero."""
    exact = Decimal(v).scaleb(d)
    near_tie = abs(abs(exact) % 1 - Decimal("0.5")) <= max(1, abs(exact)) * Decimal(2) ** -50
    if near_tie and Decimal(abs(v) * 10.0 ** d + 0.5) != abs(exact) + Decimal("0.5"):
        return  # the float product or sum rounded (by about 2**-53 of it) next to a tie: the rule's own
    q = Decimal(v).quantize(Decimal(1).scaleb(-d), rounding=ROUND_HALF_UP)  # HALF_UP: half away from zero
    want = f"{q:f}".lstrip("-") if q == 0 else f"{q:f}"
    fmt = RowFormatter([("fixed", d)])
    assert fmt.format(np.array([[v], [v], [0.0]])).decode() == f"{want}\n{want}\n{'0' if d == 0 else '0.' + '0' * d}\n"

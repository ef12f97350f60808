"""The side-by-side comparison of sessions' metrics (``haptic-acu compare``): the table, one column a
session (the session totals, then each insertion with its punctures and, at a point, its grading),
and each later session's differences from the first, per insertion, at each quantity's resolution
(:mod:`.quantities`)."""
from __future__ import annotations

from .quantities import BY_NAME, QUANTITIES, fmt, value

# per-insertion numbers whose difference from the first session goes into compare.json (by their one name)
DIFF_KEYS = tuple(q.name for q in QUANTITIES if q.path and q.unit and q.name != "t_entry_s")


def _fmt(x, spec: str) -> str:
    return "-" if x is None else format(x, spec)


def _puncture_peak(layer: str):
    def cell(i) -> str:
        peaks = [f"{p['peak_force_n']:.3f}" for p in i.get("punctures", ()) if p["layer"] == layer]
        return "/".join(peaks) or "-"
    return cell


def _quantity_row(q):
    return (q.label, lambda i: fmt(i, q))


# one row per quantity (analysis/quantities.py: the one name, label and resolution of each), and the
# punctures' peaks (the summary's punctures)
INSERTION_ROWS = tuple(_quantity_row(q) for q in QUANTITIES if q.label and q.path
                       and q.name not in ("time_in_tissue_s",)) + (
    ("skin puncture: peak |F| (N)", _puncture_peak("skin")),
    ("fat puncture: peak |F| (N)", _puncture_peak("fat")),
    ("muscle puncture: peak |F| (N)", _puncture_peak("muscle")),
)


def insertion_numbers(metrics, insertion: int | None) -> list[int]:
    """The insertion indices (0-based) to show: ``insertion`` (1-based) or all of the longest session's."""
    n = max((m["insertions"] for m in metrics), default=0)
    if insertion is not None:
        return [insertion - 1]
    return list(range(n))


def _closest(i) -> str:
    """An insertion's smallest margin to a danger structure (--point): 'name mm'."""
    m = {k: v for k, v in (i.get("danger_margin_mm") or {}).items() if v is not None}
    if not m:
        return "-"
    k = min(m, key=m.get)
    return f"{k} {m[k]:.1f}"


POINT_ROWS = (  # with --point
    ("angle error (deg)", lambda i: _fmt(i.get("angle_error_deg"), ".1f")),
    ("closest structure (mm)", _closest),
    ("critical errors", lambda i: ", ".join(e["structure"] for e in i.get("critical_errors", ())) or "none"),
)


def table_lines(labels, metrics, insertion: int | None = None) -> list[str]:
    """The side-by-side table, one column per session: totals, then each insertion shown (with
    --point, its grading against the point too)."""
    bound = metrics[0]["lateral_comfort_n"]
    lo, hi = metrics[0]["target_depth_mm"]
    rows = [
        ("insertions", [str(m["insertions"]) for m in metrics]),
        ("skin punctures", [str(m["skin_punctures"]) for m in metrics]),
        ("time in tissue (s)", [f"{m['time_in_tissue_s']:.3f}" for m in metrics]),
        (f"lateral force > {bound:g} N (s)", [f"{m['lateral']['time_over_s']:.3f}" for m in metrics]),
    ]
    for k in insertion_numbers(metrics, insertion):
        rows.append((f"insertion {k + 1} (target depth {lo:g}-{hi:g} mm):", None))
        graded = any("critical_errors" in i for m in metrics for i in m["per_insertion"])
        for name, fn in INSERTION_ROWS + (POINT_ROWS if graded else ()):
            rows.append((f"  {name}", [fn(m["per_insertion"][k]) if k < len(m["per_insertion"]) else "-"
                                       for m in metrics]))
    w0 = max(len(name) for name, _ in rows)
    widths = [max([len(lab)] + [len(cells[j]) for _, cells in rows if cells]) for j, lab in enumerate(labels)]
    out = ["  ".join([f"{'':<{w0}}"] + [f"{lab:>{w}}" for lab, w in zip(labels, widths)])]
    for name, cells in rows:
        if cells is None:
            out.append(name)
        else:
            out.append("  ".join([f"{name:<{w0}}"] + [f"{c:>{w}}" for c, w in zip(cells, widths)]).rstrip())
    return out


def differences(metrics) -> list[dict]:
    """Each later session minus the first, per insertion index both have (None where either is None)."""
    base = metrics[0]["per_insertion"]
    out = []
    for m in metrics[1:]:
        per = []
        for a, b in zip(base, m["per_insertion"]):
            per.append({k: _diff(a, b, k) for k in DIFF_KEYS})
        out.append({"insertions": m["insertions"] - metrics[0]["insertions"], "per_insertion": per})
    return out


def first_insertion_diff(metrics) -> dict:
    """B minus A for the first insertion's numbers (None where either is missing)."""
    a, b = (m["per_insertion"][0] if m["per_insertion"] else {} for m in metrics[:2])
    return {k: _diff(a, b, k) for k in DIFF_KEYS}


def _diff(a: dict, b: dict, name: str):
    """B minus A of one quantity, at its resolution (None where either has none)."""
    q = BY_NAME[name]
    va, vb = value(a, q), value(b, q)
    if va is None or vb is None:
        return None
    return round(vb - va, q.decimals) + 0.0

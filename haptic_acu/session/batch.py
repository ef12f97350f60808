"""A batch of replays' combined tables (``haptic-acu replay`` with several trajectories):
``summaries.csv`` (one row a trajectory, :func:`summary_row`), ``insertions.csv`` (one row an
insertion, :func:`insertion_rows`) and ``punctures.csv`` (one row a puncture, :func:`puncture_rows`),
each written by :func:`write_table`."""
from __future__ import annotations

import csv
from pathlib import Path

from ..base.outputs import safe_cell, write_new


def summary_row(summary: dict) -> dict:
    """summaries.csv's row: the session's numbers (each the summary's, not a second estimate), the
    first puncture of each layer, and the session-level trainee metrics."""
    row = {"trajectory": summary["trajectory"], "duration_s": summary["duration_s"], "ticks": summary["ticks"],
           "max_force_n": summary["max_force_n"], "max_tip_depth_mm": summary["max_tip_depth_mm"],
           "layers_reached": " ".join(summary["layers_reached"]), "punctures": len(summary["punctures"])}
    for p in summary["punctures"]:
        row.setdefault(f"{p['layer']}_puncture_t_s", p["t_s"])
        row.setdefault(f"{p['layer']}_peak_force_n", p["peak_force_n"])
    m = summary.get("metrics") or {}
    for key in ("insertions", "skin_punctures", "time_in_tissue_s"):
        if key in m:
            row[key] = m[key]
    for key, v in (m.get("lateral") or {}).items():
        row[f"lateral_{key}"] = v
    if "point" in summary:  # --point: the point, the patient and the grading's totals
        g = summary["point_grading"]
        row.update(point=summary["point"], patient_sex=summary["patient"]["sex"], patient_bmi=summary["patient"]["bmi"],
                   in_range=g["in_range"], on_target=g["on_target"], critical_errors=g["critical_errors"])
    return row


def flatten(d: dict, prefix: str = "") -> dict:
    """A nested metrics dict as flat CSV columns: ``a.b`` -> ``a_b``; a list of three numbers
    (a position) -> ``_x``, ``_y``, ``_z``; a list of dicts (the insertion's punctures) -> its
    count; None -> an empty cell. New metrics get their columns without a change here."""
    out = {}
    for k, v in d.items():
        name = f"{prefix}{k}"
        if isinstance(v, dict):
            out.update(flatten(v, name + "_"))
        elif isinstance(v, (list, tuple)):
            if not v or all(isinstance(x, dict) for x in v):
                out[name] = len(v)
            elif len(v) == 3:
                out.update({f"{name}_{c}": x for c, x in zip("xyz", v)})
            else:
                out[name] = " ".join(str(x) for x in v)
        else:
            out[name] = "" if v is None else v
    return out


def insertion_rows(summary: dict) -> list[dict]:
    """insertions.csv's rows: one per insertion, numbered from 1: its trainee metrics (summary.json's
    ``metrics.per_insertion``), each quantity of :mod:`haptic_acu.analysis.quantities` under its one
    name (the cohort's column), every other number flattened by :func:`flatten`."""
    from ..analysis.quantities import QUANTITIES, value

    named = [q for q in QUANTITIES if q.path]
    taken = {"_".join(q.path) for q in named}
    m = summary.get("metrics") or {}
    rows = []
    for n, ins in enumerate(m.get("per_insertion", []), 1):
        row = {"trajectory": summary["trajectory"], "insertion": n}
        for q in named:
            v = value(ins, q)
            row[q.name] = "" if v is None else v
        row.update({k: v for k, v in flatten(ins).items() if k not in taken})
        rows.append(row)
    return rows


def puncture_rows(summary: dict) -> list[dict]:
    """punctures.csv's rows: every puncture of the session (summary.json's ``punctures``) with the
    insertion it belongs to (empty if none: a puncture outside every insertion's window)."""
    ins = (summary.get("metrics") or {}).get("per_insertion", [])
    rows = []
    for n, p in enumerate(summary["punctures"], 1):
        owner = next((k for k, i in enumerate(ins, 1) if i["t_entry_s"] <= p["t_s"] <= i["t_exit_s"]), "")
        rows.append({"trajectory": summary["trajectory"], "puncture": n, "insertion": owner, **p})
    return rows


def write_table(path: Path, rows: list[dict]) -> None:
    """A CSV with the union of the rows' columns in first-seen order (header on line 1)."""
    cols: list[str] = []
    for r in rows:
        cols += [c for c in r if c not in cols]
    import io

    buf = io.StringIO(newline="")
    wr = csv.DictWriter(buf, fieldnames=cols or ["trajectory"])
    wr.writeheader()
    wr.writerows({k: safe_cell(v) for k, v in r.items()} for r in rows)  # a file named =cmd|... is text
    write_new(path, buf.getvalue())

"""The cohort's two tables, built from the manifest and the per-session records, written as Parquet
(pyarrow, with each column's unit and meaning in the field metadata) and CSV.

Column order: the manifest's columns as given (text), then for ``insertions``: ``insertion``
(1-based index within the session), ``error``, then :data:`~haptic_acu.cohort.sessions.INSERTION_COLUMNS`;
for ``sessions``: :data:`~haptic_acu.cohort.sessions.SESSION_COLUMNS`, ``mean_<metric>`` for every numeric
insertion metric, and the two hashes. A failed session has one row in each table, with its
``error`` and empty (null) metrics; a session with no insertion has no row in ``insertions``.
Rows follow the manifest's order.
"""
from __future__ import annotations

import io
import json
from pathlib import Path

import numpy as np

from .sessions import HASH_COLUMNS, INSERTION_COLUMNS, SESSION_COLUMNS, Column, Manifest, mean_columns, write_atomic

INSERTION_INDEX = Column("insertion", "", "1-based index of the insertion within its session", dtype="int64")
ERROR = Column("error", "", "why the session failed (empty when it did not)", dtype="string")


def insertion_columns() -> list[Column]:
    return [INSERTION_INDEX, ERROR] + INSERTION_COLUMNS


def session_columns() -> list[Column]:
    return SESSION_COLUMNS + mean_columns() + HASH_COLUMNS


def build(manifest: Manifest, records: dict) -> tuple[list[dict], list[dict]]:
    """(insertion rows, session rows) as dicts, for every manifest entry (``records``: session id ->
    record, see :func:`haptic_acu.cohort.sessions.replay_session`)."""
    ins_rows, ses_rows = [], []
    for e in manifest.entries:
        rec = records.get(e.session) or {"error": "not replayed", "insertions": [], "summary": None}
        base = dict(e.cells)
        err = rec.get("error") or ""
        ses = dict(base, error=err)
        ses.update(rec.get("summary") or {})
        ins = rec.get("insertions") or []
        for c in INSERTION_COLUMNS:
            if c.dtype in ("float64", "int64"):
                vals = [r[c.name] for r in ins if r.get(c.name) is not None]
                ses[f"mean_{c.name}"] = float(np.mean(vals)) if vals else None
        ses["input_sha256"] = rec.get("input_sha256")
        ses["config_sha256"] = rec.get("config_sha256")
        ses_rows.append(ses)
        if err:
            ins_rows.append(dict(base, insertion=None, error=err))
        for i, r in enumerate(ins, start=1):
            ins_rows.append(dict(base, insertion=i, error="", **r))
    return ins_rows, ses_rows


def _arrow_table(rows: list[dict], manifest_cols: list[str], cols: list[Column]):
    import pyarrow as pa

    types = {"float64": pa.float64(), "int64": pa.int64(), "bool": pa.bool_(), "string": pa.string()}
    fields, arrays = [], []
    for name in manifest_cols:
        fields.append(pa.field(name, pa.string(), metadata={"unit": "", "description": "from the manifest"}))
        arrays.append(pa.array([r.get(name) for r in rows], type=pa.string()))
    for c in cols:
        fields.append(pa.field(c.name, types[c.dtype], metadata={"unit": c.unit, "description": c.description}))
        vals = [r.get(c.name) for r in rows]
        if c.dtype == "float64":
            vals = [None if v is None else float(v) for v in vals]
        elif c.dtype == "int64":
            vals = [None if v is None else int(v) for v in vals]
        arrays.append(pa.array(vals, type=types[c.dtype]))
    return pa.Table.from_arrays(arrays, schema=pa.schema(fields))


def _bytes_parquet(table) -> bytes:
    import pyarrow.parquet as pq

    buf = io.BytesIO()
    pq.write_table(table, buf, compression="zstd")
    return buf.getvalue()


def _bytes_csv(table) -> bytes:
    """The table as CSV, its text cells neutralised (:func:`haptic_acu.base.outputs.safe_cell`: a
    manifest's ``=cmd|...`` or ``@SUM(1)`` is written as text a spreadsheet shows, never runs)."""
    import pyarrow as pa
    import pyarrow.csv as pcsv

    from ..base.outputs import safe_cell

    for i, f in enumerate(table.schema):
        if pa.types.is_string(f.type):
            table = table.set_column(i, f, pa.array([safe_cell(v) for v in table.column(i).to_pylist()],
                                                    type=pa.string()))
    buf = io.BytesIO()
    pcsv.write_csv(table, buf)
    return buf.getvalue()


def write(out: Path, manifest: Manifest, records: dict) -> dict:
    """Write ``insertions`` and ``sessions`` (.parquet and .csv) into ``out``; returns the tables
    (pyarrow) by name."""
    ins_rows, ses_rows = build(manifest, records)
    tables = {"insertions": _arrow_table(ins_rows, manifest.columns, insertion_columns()),
              "sessions": _arrow_table(ses_rows, manifest.columns, session_columns())}
    for name, t in tables.items():
        write_atomic(out / f"{name}.parquet", _bytes_parquet(t))
        write_atomic(out / f"{name}.csv", _bytes_csv(t))
    return tables


def columns_doc() -> dict:
    """{table: {column: {unit, description}}} for report.json."""
    return {"insertions": {c.name: {"unit": c.unit, "description": c.description} for c in insertion_columns()},
            "sessions": {c.name: {"unit": c.unit, "description": c.description} for c in session_columns()}}


def dumps(obj) -> str:
    return json.dumps(obj, indent=2, sort_keys=False, allow_nan=False) + "\n"

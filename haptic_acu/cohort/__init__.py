"""A class's recorded sessions replayed into tables: the manifest, jobs and resumable records
(:mod:`.sessions`), the folder brought up to date (:mod:`.update`), the local pool or Dask cluster
that runs the replays (:mod:`.run`), the Parquet/CSV tables (:mod:`.tables`) and the report and
figures (:mod:`.report`).

May import: session, analysis, servo, tissue, base, and haptic_acu.devices.
"""


def __getattr__(name):
    """``haptic_acu.cohort.read_manifest`` and the other names of the flat layout's cohort module,
    with a DeprecationWarning naming :mod:`haptic_acu.cohort.sessions`."""
    import importlib
    import warnings

    sessions = importlib.import_module(f"{__name__}.sessions")
    if name.startswith("__") or not hasattr(sessions, name):
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    warnings.warn(f"haptic_acu.cohort.{name} moved to haptic_acu.cohort.sessions.{name}", DeprecationWarning,
                  stacklevel=2)
    return getattr(sessions, name)

"""The module paths of the flat layout, kept importable for a deprecation period: ``import
haptic_acu.needle`` gives :mod:`haptic_acu.servo.step` with a :class:`DeprecationWarning` naming the new
path. Nothing in the project imports the old paths; :func:`install` is called by ``haptic_acu``."""
from __future__ import annotations

import importlib
import importlib.abc
import importlib.util
import sys
import warnings

MOVED = {  # old module (haptic_acu.<name>) -> new module under haptic_acu
    "affinity": "servo.affinity",
    "bench_cmd": "cli.bench",
    "bundled": "base.bundled",
    "calibrate_cmd": "cli.calibrate",
    "clamp": "servo.clamp",
    "cohort_cmd": "cli.cohort",
    "cohort_report": "cohort.report",
    "cohort_run": "cohort.run",
    "cohort_tables": "cohort.tables",
    "compare_cmd": "cli.compare",
    "config": "base.config",
    "cptr": "servo.cptr",
    "csvfmt": "base.csvfmt",
    "devicemodel": "servo.devicemodel",
    "engine": "session.engine",
    "errors": "base.errors",
    "fit_cmd": "cli.fit",
    "forcenet": "tissue.forcenet",
    "hdapi": "servo.hdapi",
    "insertion_stream": "analysis.insertion_stream",
    "kernelcache": "base.kernelcache",
    "mechanics": "tissue.mechanics",
    "metrics": "analysis.metrics",
    "needle": "servo.step",
    "netresponse": "tissue.netresponse",
    "objmesh": "tissue.objmesh",
    "omniloop": "servo.omniloop",
    "overrides": "base.overrides",
    "pathstream": "session.pathstream",
    "postpuncture": "tissue.postpuncture",
    "precompile": "cli.precompile",
    "progress": "base.progress",
    "recorder": "session.recorder",
    "rendering": "servo.rendering",
    "replay": "session.replay",
    "replay_cmd": "cli.replay",
    "report": "session.report",
    "rerun_log": "session.rerun_log",
    "rtloop": "servo.rtloop",
    "run_cmd": "cli.run",
    "samples": "servo.samples",
    "score_cmd": "cli.score",
    "scoring": "analysis.scoring",
    "servostate": "servo.state",
    "servotick": "servo.tick",
    "shf": "tissue.shf",
    "sink": "session.sink",
    "sinkproc": "session.sinkproc",
    "skill_metrics": "analysis.skill_metrics",
    "springback": "tissue.springback",
    "status": "session.status",
    "stylus": "servo.stylus",
    "technique": "analysis.technique",
    "tissue": "tissue.body",
    "trajectory": "session.trajectory",
    "twirl": "tissue.twirl",
    "viewer": "session.viewer",
}


class _Alias(importlib.abc.Loader):
    def __init__(self, new: str):
        self.new = new
        self.spec = None

    def create_module(self, spec):
        module = importlib.import_module(self.new)
        self.spec = module.__spec__
        return module

    def exec_module(self, module):
        module.__spec__ = self.spec  # the import machinery set the old name's spec on the real module


class _Finder(importlib.abc.MetaPathFinder):
    def find_spec(self, fullname, path=None, target=None):
        head, _, name = fullname.partition(".")
        if head != "haptic_acu" or name not in MOVED:
            return None
        new = f"haptic_acu.{MOVED[name]}"
        warnings.warn(f"{fullname} moved to {new}; the old path will be removed", DeprecationWarning,
                      stacklevel=3)
        return importlib.util.spec_from_loader(fullname, _Alias(new))


def install() -> None:
    if not any(isinstance(f, _Finder) for f in sys.meta_path):
        sys.meta_path.append(_Finder())

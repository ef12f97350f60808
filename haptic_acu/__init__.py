"""haptic-acu: a real-time haptic simulator of acupuncture needle insertion.

The tissue is three layers (skin, fat, muscle) bounded by spherical-harmonic surfaces
(:mod:`haptic_acu.shf`, :mod:`haptic_acu.tissue`); the needle meets a hexagonal mass-spring
force net on each surface (:mod:`haptic_acu.forcenet`), per-layer damping after puncture and
shape-matching springback (:mod:`haptic_acu.needle`, :mod:`haptic_acu.springback`).
"""
from importlib.metadata import PackageNotFoundError, version as _version

try:
    __version__ = _version("haptic-acu")
except PackageNotFoundError:  # running from a source tree without install
    __version__ = "0.0.0+src"

from .errors import UserError  # noqa: E402

__all__ = ["__version__", "UserError"]

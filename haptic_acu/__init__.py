"""haptic-acu: a real-time haptic simulator of acupuncture needle insertion.

The tissue is three layers (skin, fat, muscle) bounded by spherical-harmonic surfaces
(:mod:`haptic_acu.tissue.shf`, :mod:`haptic_acu.tissue.body`); the needle meets a hexagonal mass-spring
force net on each surface (:mod:`haptic_acu.tissue.forcenet`), per-layer damping after puncture and
shape-matching springback (:mod:`haptic_acu.servo.step`, :mod:`haptic_acu.tissue.springback`).
"""
import os as _os

# Single-threaded BLAS unless the user says otherwise: a 1 kHz servo thread must not compete with BLAS
# worker threads, and on these 2-core machines a threaded lstsq (4000 x 256, the tissue fit) took 3.7 s
# under load against 0.12 s single-threaded. Set before numpy is first imported through this package.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    _os.environ.setdefault(_var, "1")



def __getattr__(name):
    """``__version__``, looked up on first use (importlib.metadata scans the installed packages: a
    cost every command would pay for a number only ``--version`` prints)."""
    if name == "__version__":
        from importlib.metadata import PackageNotFoundError, version

        try:
            v = version("haptic-acu")
        except PackageNotFoundError:  # running from a source tree without install
            v = "0.0.0+src"
        globals()["__version__"] = v
        return v
    raise AttributeError(f"module 'haptic_acu' has no attribute {name!r}")


from .base.errors import UserError  # noqa: E402

__all__ = ["__version__", "UserError"]

from .base.kernelcache import guard as _guard, package_dirs as _package_dirs  # noqa: E402

# numba checks a cached kernel against its own file only: drop the caches of the package's kernel
# modules whose imports reach a changed source, before a kernel can load an old callee
# (haptic_acu/base/kernelcache.py).
_guard(_package_dirs())

from .base.moved import install as _install_moved  # noqa: E402

# the flat layout's module paths (haptic_acu.needle, ...) still import, with a DeprecationWarning
_install_moved()

"""The package's build backend: setuptools' own, asking for the precompile's build requirements only
when the wheel will carry compiled kernels.

``setup.py`` runs ``python -m haptic_acu.cli.precompile`` on the laid-out package, which imports
numpy, scipy, numba, rerun-sdk and matplotlib in the build environment: a few hundred megabytes that
pip installs into its isolated build environment first. An editable install never precompiles, nor
does a wheel built with ``HAPTIC_ACU_NO_PRECOMPILE=1``; their build environment holds setuptools and
wheel alone (pyproject.toml's ``[build-system] requires``). The pins follow ``[project]
dependencies``.
"""
from __future__ import annotations

import os

from setuptools import build_meta as _setuptools
from setuptools.build_meta import *  # noqa: F401,F403 - every other hook is setuptools' own

PRECOMPILE_REQUIRES = ["numpy>=2.0,<2.5", "scipy>=1.13,<1.18", "numba>=0.60,<0.69", "rerun-sdk>=0.41,<0.42",
                       "matplotlib>=3.8,<3.12"]


def get_requires_for_build_wheel(config_settings=None):
    extra = [] if os.environ.get("HAPTIC_ACU_NO_PRECOMPILE") else PRECOMPILE_REQUIRES
    return _setuptools.get_requires_for_build_wheel(config_settings) + extra

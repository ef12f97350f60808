"""The wheel carries its compiled kernels: after ``build_py`` has laid the package out as it will be
installed, ``python -m haptic_acu.cli.precompile`` runs on that copy, so numba's caches (in each
subpackage's ``__pycache__``, keyed by the sources' contents, the Python and numba versions and the
CPU) and the net-response and body tables (``haptic_acu/_bundled/tables``) go into the wheel. On a
machine like the builder's the first command after ``pip install`` loads them instead of compiling
for a minute; elsewhere numba compiles as it always did. Set ``HAPTIC_ACU_NO_PRECOMPILE=1`` to
build without them (an editable install never runs it). Everything else is in pyproject.toml."""
import os
import shutil
import subprocess
import sys
from pathlib import Path

from setuptools import setup
from setuptools.command.build_py import build_py


class BuildPyWithKernels(build_py):
    def run(self):
        super().run()
        if getattr(self, "editable_mode", False):
            return
        lib = Path(self.build_lib).resolve()
        tables = lib / "haptic_acu" / "_bundled" / "tables"
        # an earlier build's caches and tables left in the build folder never go into this wheel
        shutil.rmtree(tables, ignore_errors=True)
        for f in (lib / "haptic_acu").rglob("__pycache__/*"):
            if f.suffix in (".nbi", ".nbc") or f.name.startswith("haptic_acu-kernels."):  # the guard's record
                f.unlink()
        if os.environ.get("HAPTIC_ACU_NO_PRECOMPILE"):
            return
        tables.mkdir(parents=True, exist_ok=True)
        env = {k: v for k, v in os.environ.items() if k != "NUMBA_CACHE_DIR"}
        # the laid-out package first, then the build environment's own path (pip's isolated
        # environment is reached through PYTHONPATH)
        path = [str(lib)] + ([env["PYTHONPATH"]] if env.get("PYTHONPATH") else [])
        env.update(PYTHONPATH=os.pathsep.join(path), HAPTIC_ACU_CACHE=str(tables), NUMBA_DISABLE_JIT="0")
        print("haptic-acu: compiling the kernels into the wheel (python -m haptic_acu.cli.precompile)", file=sys.stderr)
        r = subprocess.run([sys.executable, "-m", "haptic_acu.cli.precompile"], cwd=str(tables), env=env)
        if r.returncode != 0:  # e.g. numba not importable here: a wheel that compiles on first use
            print("haptic-acu: precompiling failed; the wheel's kernels compile on first use", file=sys.stderr)


setup(cmdclass={"build_py": BuildPyWithKernels})

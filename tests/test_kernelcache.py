"""The kernel-cache guard (haptic_acu/base/kernelcache.py) against numba's own behaviour: a cached kernel
that calls a function of another module keeps the callee's old code when only the callee's file
changes. A two-module toy package shows the stale result without the guard and the new one with it."""
from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

from haptic_acu.base import kernelcache

ROOT = Path(__file__).resolve().parent.parent

CALLER = """
import numba as nb
from .callee import f

@nb.njit(cache=True)
def g(x):
    return f(x) + 1.0
"""

CALLEE = """
import numba as nb

@nb.njit(cache=True)
def f(x):
    return {body}
"""


def make_pkg(root: Path, body: str) -> Path:
    pkg = root / "toypkg"
    pkg.mkdir(exist_ok=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "caller.py").write_text(CALLER)
    (pkg / "callee.py").write_text(CALLEE.format(body=body))
    return pkg


def run_g(root: Path, guarded: bool) -> float:
    code = textwrap.dedent(f"""
        import sys
        from pathlib import Path
        sys.path.insert(0, {str(ROOT)!r})
        sys.path.insert(0, {str(root)!r})
        if {guarded!r}:
            from haptic_acu.base.kernelcache import guard
            guard([Path({str(root / 'toypkg')!r})])
        from toypkg.caller import g
        print(g(2.0))
        """)
    env = {k: v for k, v in __import__("os").environ.items() if k != "NUMBA_CACHE_DIR"}
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300, env=env)
    assert r.returncode == 0, r.stderr
    return float(r.stdout.strip().splitlines()[-1])


def test_numba_keeps_a_stale_callee_and_the_guard_drops_it(tmp_path):
    for guarded in (False, True):
        root = tmp_path / ("guarded" if guarded else "plain")
        root.mkdir()
        make_pkg(root, "x * 2.0")
        assert run_g(root, guarded) == 5.0
        assert any(p.suffix == ".nbi" for p in (root / "toypkg" / "__pycache__").iterdir())
        make_pkg(root, "x * 10.0")  # only the callee's file changes
        got = run_g(root, guarded)
        if guarded:
            assert got == 21.0  # recompiled against the new callee
        else:
            assert got == 5.0  # numba's cache alone: the caller still inlines the old callee


def test_guard_removes_only_numba_cache_files_and_only_on_a_change(tmp_path):
    pkg = make_pkg(tmp_path, "x")
    pc = pkg / "__pycache__"
    pc.mkdir()
    (pc / "caller.g-5.py311.nbi").write_text("i")
    (pc / "caller.g-5.py311.1.nbc").write_text("c")
    (pc / "caller.cpython-311.pyc").write_text("p")
    (pkg / "notes.nbi.txt").write_text("a user's file")
    assert kernelcache.guard([pkg]) is True  # no digest yet: the caches cannot be trusted
    assert sorted(p.name for p in pc.iterdir()) == ["caller.cpython-311.pyc", kernelcache.STAMP]
    assert (pkg / "notes.nbi.txt").read_text() == "a user's file"
    (pc / "caller.g-5.py311.nbi").write_text("i")
    assert kernelcache.guard([pkg]) is False  # sources unchanged: caches kept
    assert (pc / "caller.g-5.py311.nbi").exists()
    (pkg / "callee.py").write_text((pkg / "callee.py").read_text() + "\n# edited\n")
    assert kernelcache.guard([pkg]) is True
    assert not (pc / "caller.g-5.py311.nbi").exists()


def test_digest_follows_content_and_names(tmp_path):
    pkg = make_pkg(tmp_path, "x")
    d0 = kernelcache.source_digest([pkg])
    assert kernelcache.source_digest([pkg]) == d0
    (pkg / "callee.py").write_text((pkg / "callee.py").read_text() + " ")
    d1 = kernelcache.source_digest([pkg])
    assert d1 != d0
    (pkg / "callee.py").rename(pkg / "callee2.py")
    assert kernelcache.source_digest([pkg]) != d1


def test_the_package_keeps_a_digest_of_its_own_sources():
    dirs = kernelcache.package_dirs()
    assert dirs[0] == ROOT / "haptic_acu" and ROOT / "devices" in dirs and ROOT / "bench" in dirs
    stamp = dirs[0] / "__pycache__" / kernelcache.STAMP
    assert stamp.read_text().strip() == kernelcache.source_digest(dirs)  # written at import

"""The kernel-cache guard (haptic_acu/base/kernelcache.py) against numba's own behaviour: a cached kernel
that calls a function of another module keeps the callee's old code when only the callee's file
changes. A toy package shows the stale result without the guard, the new one with it, and the
cache kept when a module the kernel does not import changes. Fake packages with fake cache files
show which modules' caches the guard removes."""
from __future__ import annotations

import json
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from haptic_acu.base import kernelcache

ROOT = Path(__file__).resolve().parent.parent

CALLER = """
import numba as nb
from .callee import f

@nb.njit(cache=True)
def g(x):
    return f(x) + 1.0
"""

UNRELATED = """
def h(x):
    return x
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
    if not (pkg / "unrelated.py").exists():
        (pkg / "unrelated.py").write_text(UNRELATED)
    return pkg


def run_g(root: Path, guarded: bool) -> tuple[float, int]:
    """g(2.0) in a fresh interpreter, and how many of g's compiled versions numba loaded from its cache."""
    code = textwrap.dedent(f"""
        import sys
        from pathlib import Path
        sys.path.insert(0, {str(ROOT)!r})
        sys.path.insert(0, {str(root)!r})
        if {guarded!r}:
            from haptic_acu.base.kernelcache import guard
            guard([Path({str(root / 'toypkg')!r})])
        from toypkg.caller import g
        print(g(2.0), sum(g.stats.cache_hits.values()))
        """)
    env = {k: v for k, v in __import__("os").environ.items() if k != "NUMBA_CACHE_DIR"}
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300, env=env)
    assert r.returncode == 0, r.stderr
    value, hits = r.stdout.split()
    return float(value), int(hits)


def test_numba_keeps_a_stale_callee_and_the_guard_drops_it(tmp_path):
    for guarded in (False, True):
        root = tmp_path / ("guarded" if guarded else "plain")
        root.mkdir()
        make_pkg(root, "x * 2.0")
        assert run_g(root, guarded) == (5.0, 0)
        assert any(p.suffix == ".nbi" for p in (root / "toypkg" / "__pycache__").iterdir())
        if guarded:  # a module the kernel does not import changes: the kernel still loads from the cache
            (root / "toypkg" / "unrelated.py").write_text(UNRELATED + "\n# edited\n")
            assert run_g(root, guarded) == (5.0, 1)
        make_pkg(root, "x * 10.0")  # only the callee's file changes
        if guarded:
            assert run_g(root, guarded) == (21.0, 0)  # recompiled against the new callee
        else:
            assert run_g(root, guarded) == (5.0, 1)  # numba's cache alone: the caller still inlines the old callee


def test_guard_removes_only_numba_cache_files_and_only_on_a_change(tmp_path):
    pkg = make_pkg(tmp_path, "x")
    pc = pkg / "__pycache__"
    pc.mkdir()
    (pc / "caller.g-5.py311.nbi").write_text("i")
    (pc / "caller.g-5.py311.1.nbc").write_text("c")
    (pc / "caller.cpython-311.pyc").write_text("p")
    (pkg / "notes.nbi.txt").write_text("a user's file")
    assert kernelcache.guard([pkg]) is True  # no record yet: the caches cannot be trusted
    assert sorted(p.name for p in pc.iterdir()) == ["caller.cpython-311.pyc", kernelcache.STAMP]
    assert (pkg / "notes.nbi.txt").read_text() == "a user's file"
    (pc / "caller.g-5.py311.nbi").write_text("i")
    assert kernelcache.guard([pkg]) is False  # sources unchanged: caches kept
    assert (pc / "caller.g-5.py311.nbi").exists()
    (pkg / "callee.py").write_text((pkg / "callee.py").read_text() + "\n# edited\n")
    assert kernelcache.guard([pkg]) is True
    assert not (pc / "caller.g-5.py311.nbi").exists()


# A package of kernel modules (fake cache files) and the modules they import, directly or not:
#   kern_a -> mid (relative, inside a function) -> sub/consts; sub/kern_b -> sub (absolute) -> sub/consts;
#   kern_c imports nothing of the package; cli imports kern_a but no kernel imports cli.
FAKE = {
    "__init__.py": "",
    "kern_a.py": "import numba\nfrom .mid import f\n",
    "mid.py": "def make():\n    from .sub.consts import K\n    return K\nf = make\n",
    "sub/__init__.py": "from .consts import K\n",
    "sub/consts.py": "K = 2.0\n",
    "sub/kern_b.py": "import fakepkg.sub as s\n",
    "kern_c.py": "import numpy as np\n",
    "cli.py": "from .kern_a import f\nfrom . import kern_c\n",
}
KERNELS = ["kern_a", "sub/kern_b", "kern_c"]


def fake_pkg(root: Path) -> Path:
    pkg = root / "fakepkg"
    for name, text in FAKE.items():
        (pkg / name).parent.mkdir(parents=True, exist_ok=True)
        (pkg / name).write_text(text)
    return pkg


def add_caches(pkg: Path, module: str) -> None:
    """Files named as numba names a kernel's index and data in the module's ``__pycache__``."""
    d, name = (pkg / module).parent, (pkg / module).name
    (d / "__pycache__").mkdir(exist_ok=True)
    for suffix in (".py311.nbi", ".py311.1.nbc"):
        (d / "__pycache__" / f"{name}.kern-3{suffix}").write_text("cache")


def cached(pkg: Path) -> list[str]:
    """The modules that have numba cache files, by the cache files' names."""
    found = {f.parent.parent.relative_to(pkg) / f.name.split(".")[0] for f in kernelcache.cache_files([pkg])}
    return sorted(p.as_posix() for p in found)


def edit(path: Path) -> None:
    path.write_text(path.read_text() + "\n# edited\n")


@pytest.fixture
def pkg(tmp_path):
    pkg = fake_pkg(tmp_path)
    kernelcache.guard([pkg])  # the first record
    for m in KERNELS:
        add_caches(pkg, m)
    assert cached(pkg) == sorted(KERNELS)
    return pkg


def test_an_edit_no_kernel_imports_keeps_every_cache(pkg):
    edit(pkg / "cli.py")
    assert kernelcache.guard([pkg]) is False
    assert cached(pkg) == sorted(KERNELS)
    (pkg / "tool.py").write_text("from . import kern_a\n")  # a new module nothing imports
    assert kernelcache.guard([pkg]) is False
    assert cached(pkg) == sorted(KERNELS)


def test_an_edit_removes_exactly_the_kernels_that_import_it(pkg):
    edit(pkg / "sub" / "consts.py")  # kern_a through mid; kern_b through the package sub
    assert kernelcache.guard([pkg]) is True
    assert cached(pkg) == ["kern_c"]
    for m in KERNELS:
        add_caches(pkg, m)
    edit(pkg / "mid.py")
    assert kernelcache.guard([pkg]) is True
    assert cached(pkg) == ["kern_c", "sub/kern_b"]
    add_caches(pkg, "kern_a")
    edit(pkg / "kern_c.py")  # a kernel module's own file
    assert kernelcache.guard([pkg]) is True
    assert cached(pkg) == ["kern_a", "sub/kern_b"]


def test_a_new_kernel_module_and_a_new_import_are_followed(pkg):
    (pkg / "sub" / "kern_d.py").write_text("from ..mid import f\n")
    assert kernelcache.guard([pkg]) is False
    add_caches(pkg, "sub/kern_d")
    edit(pkg / "sub" / "consts.py")
    assert kernelcache.guard([pkg]) is True
    assert cached(pkg) == ["kern_c"]
    for m in [*KERNELS, "sub/kern_d"]:
        add_caches(pkg, m)
    (pkg / "kern_c.py").write_text("from .sub import consts\n")  # kern_c now reads consts
    assert kernelcache.guard([pkg]) is True
    assert cached(pkg) == ["kern_a", "sub/kern_b", "sub/kern_d"]
    add_caches(pkg, "kern_c")
    edit(pkg / "sub" / "consts.py")
    kernelcache.guard([pkg])
    assert cached(pkg) == []


def test_a_removed_module_and_a_numba_extension_reach_every_kernel(pkg):
    (pkg / "sub" / "consts.py").unlink()
    assert kernelcache.guard([pkg]) is True
    assert cached(pkg) == ["kern_c"]
    for m in KERNELS:
        add_caches(pkg, m)
    # a kernel uses an @overload without importing the module that registers it
    (pkg / "ext.py").write_text("from numba.extending import overload\n")
    kernelcache.guard([pkg])
    assert cached(pkg) == []


def test_caches_of_a_removed_source_go_with_the_next_change(pkg):
    (pkg / "kern_c.py").unlink()
    assert kernelcache.guard([pkg]) is True
    assert cached(pkg) == ["kern_a", "sub/kern_b"]


def test_imports_follow_relative_absolute_and_nested_imports():
    src = textwrap.dedent("""
        from __future__ import annotations
        import numpy as np
        import fakepkg.sub.consts
        from . import mid
        from ..base import config, errors as e
        def f():
            try:
                from .deep.inner import (g,
                                         h)
            except ImportError:
                import fakepkg.other
        """).encode()
    names, hooks = kernelcache.imports(src, "fakepkg.sub.kern", is_package=False)
    assert set(names) == {
        "fakepkg", "fakepkg.sub", "fakepkg.sub.consts", "fakepkg.sub.mid", "fakepkg.base", "fakepkg.base.config",
        "fakepkg.base.errors", "fakepkg.sub.deep", "fakepkg.sub.deep.inner", "fakepkg.sub.deep.inner.g",
        "fakepkg.sub.deep.inner.h", "fakepkg.other"}
    assert hooks is False
    # in a package's __init__, "." is the package itself
    assert kernelcache.imports(b"from .x import y", "fakepkg.sub", is_package=True)[0] == [
        "fakepkg", "fakepkg.sub", "fakepkg.sub.x", "fakepkg.sub.x.y"]


def test_a_bad_record_a_bad_source_or_an_unwritable_record_never_raise(pkg, monkeypatch):
    stamp = pkg / "__pycache__" / kernelcache.STAMP
    for bad in ("not json", "[1, 2]", '{"fakepkg": 3}', '{"fakepkg": [1, 2, 3]}'):
        stamp.write_text(bad)
        for m in KERNELS:
            add_caches(pkg, m)
        assert kernelcache.guard([pkg]) is True  # no usable record: no cache is trusted
        assert cached(pkg) == []
    add_caches(pkg, "kern_c")
    (pkg / "sub" / "broken.py").write_text("def (:\n")  # a source that does not parse; nothing imports it
    assert kernelcache.guard([pkg]) is False
    assert cached(pkg) == ["kern_c"]
    stamp.unlink()
    stamp.mkdir()  # the record can be neither read nor replaced
    assert kernelcache.guard([pkg]) is False
    assert kernelcache.guard([pkg / "missing"]) is False
    add_caches(pkg, "kern_a")
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(pkg))  # numba caches elsewhere: nothing to guard
    edit(pkg / "mid.py")
    assert kernelcache.guard([pkg]) is False
    assert cached(pkg) == ["kern_a"]


def test_the_package_keeps_a_record_of_its_own_sources():
    dirs = kernelcache.package_dirs()
    assert dirs[0] == ROOT / "haptic_acu" and ROOT / "devices" in dirs and ROOT / "bench" in dirs
    stamp = dirs[0] / "__pycache__" / kernelcache.STAMP
    files = kernelcache.sources(dirs)
    assert files["haptic_acu.devices.scripted"] == ROOT / "devices" / "scripted.py"
    record = json.loads(stamp.read_text())  # written at import
    assert kernelcache.scan(files, record) == record
    # the servo step's kernels compile in the tissue's surfaces; the replay command is no kernel's source
    sources_of_step = kernelcache.closure({"haptic_acu.servo.step"}, {m: v[1] for m, v in record.items()})
    assert "haptic_acu.tissue.shf" in sources_of_step and "haptic_acu.cli.replay" not in sources_of_step

"""The code's shape rules (issue 11), checked on the project's own sources with ``ast`` so they stay
true: no Python function longer than MAX_LINES lines, no compiled function (numba ``njit`` / ``jit``
/ ``cfunc`` / ``register_jitable`` / ``intrinsic``) with more than MAX_PARAMS parameters (kernels
take named inputs: NamedTuples of arrays, record dtypes)."""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("haptic_acu", "devices", "bench", "tools")
MAX_LINES = 120
MAX_PARAMS = 8
COMPILERS = {"njit", "jit", "cfunc", "register_jitable", "intrinsic", "generated_jit", "vectorize"}


def sources():
    for pkg in PACKAGES:
        yield from sorted((ROOT / pkg).rglob("*.py"))


def functions(tree):
    for node in ast.walk(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            yield node


def compiler_of(dec) -> str | None:
    """The compiling decorator's name (``nb.njit(...)``, ``njit``, ``numba.cfunc(sig)``...), or None."""
    if isinstance(dec, ast.Call):
        dec = dec.func
    name = dec.attr if isinstance(dec, ast.Attribute) else dec.id if isinstance(dec, ast.Name) else None
    return name if name in COMPILERS else None


def n_params(fn) -> int:
    a = fn.args
    return len(a.posonlyargs) + len(a.args) + len(a.kwonlyargs) + (a.vararg is not None) + (a.kwarg is not None)


def where(path, fn) -> str:
    return f"{path.relative_to(ROOT)}:{fn.lineno} {fn.name}"


def test_the_checks_see_the_code():
    # The walk finds the packages and the compiled kernels (a rule over nothing would pass).
    files = list(sources())
    assert len(files) > 40
    compiled = [fn for p in files for fn in functions(ast.parse(p.read_text())) if any(map(compiler_of, fn.decorator_list))]
    assert len(compiled) > 50


def test_no_function_over_max_lines():
    long = [f"{where(p, fn)}: {fn.end_lineno - fn.lineno + 1} lines" for p in sources()
            for fn in functions(ast.parse(p.read_text())) if fn.end_lineno - fn.lineno + 1 > MAX_LINES]
    assert not long, "functions over %d lines:\n%s" % (MAX_LINES, "\n".join(long))


def test_no_compiled_function_over_max_params():
    wide = [f"{where(p, fn)}: {n_params(fn)} parameters" for p in sources()
            for fn in functions(ast.parse(p.read_text()))
            if any(map(compiler_of, fn.decorator_list)) and n_params(fn) > MAX_PARAMS]
    assert not wide, "compiled functions over %d parameters:\n%s" % (MAX_PARAMS, "\n".join(wide))


@pytest.mark.parametrize("src, lines, params", [
    ("def f(a, b):\n" + "    x = 1\n" * 130, 131, None),
    ("import numba as nb\n@nb.njit(cache=True)\ndef g(a, b, c, d, e, f, g, h, i):\n    return a\n", None, 9),
    ("from numba import cfunc\n@cfunc('void()')\ndef h(*a, k=1):\n    pass\n", None, 2),
])
def test_the_measures_on_known_code(src, lines, params):
    fn = next(functions(ast.parse(src)))
    if lines is not None:
        assert fn.end_lineno - fn.lineno + 1 == lines
    if params is not None:
        assert any(map(compiler_of, fn.decorator_list)) and n_params(fn) == params

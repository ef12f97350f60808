"""The code's shape rules, checked on the project's own sources with ``ast`` so they stay
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


# ---- the review's other findings, kept true the same way --------------------------------
VOCABULARY = {"N_LAYERS", "N_SLOTS", "MAX_TRACKS", "MAX_HOLES", "LAYER_NAMES", "PLACE_NAMES", "STATE_NAMES",
              "UNTOUCHED", "PRESSING", "PUNCTURED", "FREE", "SERVO_OWNS", "VISUAL_OWNS",
              "OUTSIDE", "SKIN", "FAT", "MUSCLE", "BONE"}
# where the vocabulary is declared (config.py: the layer names a config file uses), and the NumPy
# reference, an independent re-implementation on purpose
VOCABULARY_HOMES = {"haptic_acu/tissue/layers.py", "haptic_acu/base/config.py", "bench/numpy_reference.py"}
# the engine's side of the device interface: it uses what devices.base.Device declares
ENGINE_SIDE = ("haptic_acu/session/engine.py", "haptic_acu/servo/tick.py", "haptic_acu/servo/rtloop.py", "haptic_acu/servo/omniloop.py")
# the servo core and the engine: imports run one way, devices/ -> haptic_acu (the commands that build a
# device import devices/)
CORE = ("servo/state", "servo/step", "servo/tick", "servo/rtloop", "servo/omniloop", "session/engine", "servo/samples",
        "servo/rendering", "servo/devicemodel", "tissue/mechanics", "tissue/postpuncture", "tissue/twirl", "servo/clamp",
        "tissue/netresponse", "tissue/forcenet", "tissue/shf", "tissue/body", "tissue/springback")


def rel(path) -> str:
    return path.relative_to(ROOT).as_posix()


def literal_value(node):
    try:
        return ast.literal_eval(node)
    except (ValueError, SyntaxError, TypeError):
        return None


def vocabulary_declarations(tree):
    """(line, name) of module-level assignments of a vocabulary name to a literal (an import or an
    expression of other names is not a declaration)."""
    for node in tree.body:
        if isinstance(node, ast.Assign):
            for tgt in node.targets:
                names = tgt.elts if isinstance(tgt, ast.Tuple) else [tgt]
                for n in names:
                    if isinstance(n, ast.Name) and n.id in VOCABULARY and literal_value(node.value) is not None:
                        yield node.lineno, n.id


def layer_name_literals(tree):
    """Lines of tuple or list literals spelling the layer names ("skin", "fat", "muscle"...)."""
    for node in ast.walk(tree):
        if isinstance(node, (ast.Tuple, ast.List)):
            v = literal_value(node)
            if isinstance(v, (tuple, list)) and tuple(v[:3]) == ("skin", "fat", "muscle"):
                yield node.lineno


def device_probes(tree):
    """(line, what) of getattr / hasattr on a device, and reads of a device's private fields."""
    def is_device(n):
        return (isinstance(n, ast.Name) and n.id in ("dev", "device")) or (
            isinstance(n, ast.Attribute) and n.attr == "device")
    for node in ast.walk(tree):
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id in ("getattr", "hasattr") \
                and node.args and is_device(node.args[0]):
            yield node.lineno, f"{node.func.id}(device, ...)"
        if isinstance(node, ast.Attribute) and node.attr.startswith("_") and not node.attr.startswith("__") \
                and is_device(node.value):
            yield node.lineno, f"device.{node.attr}"


def imports_devices(tree) -> list[int]:
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module and "devices" in node.module.split("."):
            out.append(node.lineno)
        elif isinstance(node, ast.Import) and any("devices" in a.name.split(".") for a in node.names):
            out.append(node.lineno)
    return out


def test_the_vocabulary_is_declared_once():
    found = [f"{rel(p)}:{line} {name}" for p in sources() if rel(p) not in VOCABULARY_HOMES
             for line, name in vocabulary_declarations(ast.parse(p.read_text()))]
    found += [f"{rel(p)}:{line} a literal list of the layer names" for p in sources()
              if rel(p) not in VOCABULARY_HOMES for line in layer_name_literals(ast.parse(p.read_text()))]
    assert not found, "the model's vocabulary re-declared (import it from haptic_acu.tissue.layers):\n" + "\n".join(found)


def test_the_engine_uses_only_the_declared_device_interface():
    found = [f"{name}:{line} {what}" for name in ENGINE_SIDE
             for line, what in device_probes(ast.parse((ROOT / name).read_text()))]
    assert not found, "the engine probes a device or reads its private fields:\n" + "\n".join(found)


def test_the_core_never_imports_devices():
    found = [f"haptic_acu/{m}.py:{line}" for m in CORE
             for line in imports_devices(ast.parse((ROOT / "haptic_acu" / f"{m}.py").read_text()))]
    assert not found, "imports run devices/ -> haptic_acu, never back from the core:\n" + "\n".join(found)


@pytest.mark.parametrize("src, vocab, names, probes, imports", [
    ("N_LAYERS = 3\nPRESSING, PUNCTURED = 1, 2\nfrom x import FREE\nN_SLOTS = len(A)\n", 3, 0, 0, 0),
    ("X = ('skin', 'fat', 'muscle')\nY = [*A, 'skin']\n", 0, 1, 0, 0),
    ("def f(dev, self):\n    getattr(dev, 'x', None)\n    self.device._handle\n    hasattr(other, 'y')\n", 0, 0, 2, 0),
    ("from haptic_acu.devices.scripted import S\nimport devices.base\nfrom .servostate import N\n", 0, 0, 0, 2),
])
def test_the_review_checks_on_known_code(src, vocab, names, probes, imports):
    tree = ast.parse(src)
    assert len(list(vocabulary_declarations(tree))) == vocab
    assert len(list(layer_name_literals(tree))) == names
    assert len(list(device_probes(tree))) == probes
    assert len(imports_devices(tree)) == imports

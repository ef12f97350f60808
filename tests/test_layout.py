"""The package layout is the architecture: every import (module-level or inside a function) of
haptic_acu's modules, devices/ and bench/ is read from the source and checked against the direction

    cli -> cohort | study -> session -> analysis -> servo -> tissue -> base

(a package may import itself and the packages to its right), with ``devices`` between session and
servo (a device may import base, servo and the trajectory format), and with no import circle between
modules. The graph is built from the AST, so a lazy import counts as much as one at the top."""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
CHAIN = ["cli", "cohort", "session", "analysis", "servo", "tissue", "base"]
ALLOWED = {pkg: set(CHAIN[i:]) for i, pkg in enumerate(CHAIN)}
ALLOWED["cli"] |= {"devices", "bench", "study"}
ALLOWED["cohort"] |= {"devices"}
ALLOWED["study"] = ALLOWED["cohort"] - {"cohort"}  # the blinded user study: beside cohort
ALLOWED["study"] = {"study"} | set(CHAIN[2:])  # beside cohort: session and the packages to its right
ALLOWED["session"] |= {"devices"}
ALLOWED["devices"] = {"devices", "base", "servo"}
DEVICE_EXCEPTIONS = {"haptic_acu.session.trajectory"}  # the recorded-path format a scripted device reads
ALLOWED["bench"] = set(CHAIN) | {"devices", "bench"}


def sources() -> dict[str, Path]:
    """Module name -> file for the package, devices/ and bench/ (as installed: haptic_acu.devices...)."""
    out = {}
    for f in (ROOT / "haptic_acu").rglob("*.py"):
        parts = list(f.relative_to(ROOT).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = f
    for top in ("devices", "bench"):
        for f in (ROOT / top).glob("*.py"):
            name = f"haptic_acu.{top}" + ("" if f.stem == "__init__" else f".{f.stem}")
            out[name] = f
    return out


def _resolve(module: str, is_pkg: bool, node: ast.ImportFrom) -> str:
    if node.level == 0:
        return node.module or ""
    base = module.split(".") if is_pkg else module.split(".")[:-1]
    base = base[: len(base) - (node.level - 1)]
    return ".".join(base + ([node.module] if node.module else []))


def imports_of(module: str, path: Path, known: set[str]) -> set[str]:
    """The haptic_acu modules ``module`` imports anywhere in its source."""
    tree = ast.parse(path.read_text(), filename=str(path))
    is_pkg = path.name == "__init__.py"
    found = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            src = _resolve(module, is_pkg, node)
            names = [f"{src}.{a.name}" for a in node.names] + [src]
        else:
            continue
        for name in names:
            while name and name not in known:  # `from pkg import mod` names a module; `from mod import f` does not
                name = name.rpartition(".")[0]
            if name.startswith("haptic_acu.") and name != module:
                found.add(name)
    return found


def package_of(module: str) -> str | None:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else None


@pytest.fixture(scope="module")
def graph() -> dict[str, set[str]]:
    src = sources()
    return {m: imports_of(m, p, set(src)) for m, p in src.items()}


def test_every_module_lives_in_a_subpackage():
    top = sorted(p.name for p in (ROOT / "haptic_acu").glob("*.py"))
    assert top == ["__init__.py", "__main__.py"], top


def test_every_subpackage_says_what_lives_there_and_what_it_may_import():
    for pkg in CHAIN:
        doc = ast.get_docstring(ast.parse((ROOT / "haptic_acu" / pkg / "__init__.py").read_text())) or ""
        assert "import" in doc.lower() and len(doc.splitlines()) <= 12, pkg


def test_imports_follow_the_direction(graph):
    bad = []
    for mod, deps in graph.items():
        here = package_of(mod)
        if here is None or here not in ALLOWED:
            continue
        for dep in deps:
            there = package_of(dep)
            if there is None or there in ALLOWED[here]:
                continue
            if here == "devices" and dep in DEVICE_EXCEPTIONS:
                continue
            bad.append(f"{mod} -> {dep}")
    assert not bad, "imports against the direction:\n" + "\n".join(sorted(bad))


def test_no_import_circles(graph):
    """Tarjan's strongly connected components of the module graph: every component is one module."""
    index, low, on, stack, comps = {}, {}, set(), [], []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in graph.get(v, ()):
            if w not in graph:
                continue
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            comps.append(comp)

    for v in sorted(graph):
        if v not in index:
            visit(v)
    # a package's __init__ re-exporting its own modules is not a circle
    circles = [sorted(c) for c in comps if len(c) > 1]
    assert not circles, f"import circles: {circles}"


def test_the_checker_sees_a_violation(tmp_path):
    """The walk is not vacuous: a servo module importing the session is caught, a lazy import too."""
    f = tmp_path / "x.py"
    f.write_text("def f():\n    from ..session import engine\n")
    known = {"haptic_acu.servo.x", "haptic_acu.session", "haptic_acu.session.engine"}
    assert "haptic_acu.session.engine" in imports_of("haptic_acu.servo.x", f, known)


# A command module parses its arguments, calls the package that does the work and prints or writes
# the results: apart from its ``register`` (the argparse declaration, as long as the command's
# options), it stays short, and so does each of its functions.
CLI_MAX_LINES = 260  # a cli module's lines outside ``register``
CLI_MAX_FUNCTION_LINES = 60  # a cli function's lines, ``register`` aside


def cli_shape() -> dict[str, tuple[int, list[tuple[str, int]]]]:
    """cli module -> (its lines outside ``register``, [(function, lines)] of its other functions)."""
    out = {}
    for f in sorted((ROOT / "haptic_acu" / "cli").glob("*.py")):
        text = f.read_text()
        tree = ast.parse(text, filename=str(f))
        fns = [(n.name, n.end_lineno - n.lineno + 1) for n in ast.walk(tree)
               if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef))]
        register = sum(n for name, n in fns if name == "register")
        out[f.name] = (len(text.splitlines()) - register, [(name, n) for name, n in fns if name != "register"])
    return out


def test_cli_modules_stay_thin():
    shape = cli_shape()
    assert len(shape) >= 10 and sum(n for n, _ in shape.values()) > 1000  # the walk sees the commands
    long_modules = [f"haptic_acu/cli/{m}: {n} lines outside register" for m, (n, _) in shape.items()
                    if n > CLI_MAX_LINES]
    long_functions = [f"haptic_acu/cli/{m}: {name} {n} lines" for m, (_, fns) in shape.items()
                      for name, n in fns if n > CLI_MAX_FUNCTION_LINES]
    assert not long_modules and not long_functions, (
        "a command's work belongs in the package named for it (session/, analysis/, cohort/, study/, "
        "tissue/), not in cli/:\n" + "\n".join(long_modules + long_functions))

"""The package's shape: layers that point one way (issue 25), no Prefect in the library, no
import cycles, no private names imported across modules, and no function longer than the
limit (issue 12)."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
LIBRARY = ROOT / "fieldcal"
MAX_FUNCTION_LINES = 100  # issue 12: long functions broken into their named steps

LAYERS: tuple[tuple[str, tuple[str, ...]], ...] = (
    # bottom: the contract every layer may name
    ("contract", ("fieldcal", "fieldcal.errors", "fieldcal.contract", "fieldcal.progress")),
    ("model", ("fieldcal.model", "fieldcal.robust")),
    ("solver", ("fieldcal.solver",)),
    ("measure", ("fieldcal.measure",)),
    ("session", ("fieldcal.session",)),
    ("analysis", ("fieldcal.analysis",)),
    ("methods", ("fieldcal.field", "fieldcal.goniometer", "fieldcal.rig")),
    ("lake", ("fieldcal.lake",)),
    ("runs", ("fieldcal.pipeline", "fieldcal.rig_run", "fieldcal.batch", "fieldcal.fleet")),
    ("products", ("fieldcal.products",)),
    ("tools", ("fieldcal.synthetic", "fieldcal.precompile")),
    ("flows", ("flows",)),
    # top
)
"""fieldcal's layers, bottom first (docs/architecture.md draws them): a module imports from
its own layer or the layers below it, never from above. A name here is a package or a
module; a module belongs to the longest name that prefixes it."""


def _modules(top: Path, package: str):
    for path in sorted(top.rglob("*.py")):
        rel = path.relative_to(top).with_suffix("")
        parts = [package, *rel.parts]
        if parts[-1] == "__init__":
            parts = parts[:-1]
        yield ".".join(parts), path


def _imports(module: str, path: Path):
    """(imported module, imported names, line) of every import in the file, at any depth."""
    tree = ast.parse(path.read_text())
    is_pkg = path.name == "__init__.py"
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                yield a.name, [], node.lineno
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = module.split(".")
                base = base[: len(base) - node.level + (1 if is_pkg else 0)]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            yield target, [a.name for a in node.names], node.lineno


def test_the_library_never_imports_prefect():
    code = ("import importlib, pkgutil, sys, fieldcal\n"
            "for m in pkgutil.walk_packages(fieldcal.__path__, 'fieldcal.'):\n"
            "    importlib.import_module(m.name)\n"
            "print(sorted(k for k in sys.modules if k == 'prefect' or k.startswith('prefect.')))\n")
    assert _printed_by_a_fresh_interpreter(code) == "[]"


def test_the_solve_step_does_not_import_scipy_stats_or_optimize():
    """The solve step a user waits for imports what it uses: scipy.stats alone takes 0.6-0.9 s
    to import (its distributions' docstrings), for two chi-square quantiles that scipy.special
    gives bit for bit (issue 15, goal 3: it was in the first identification's time)."""
    code = ("import sys\n"
            "import fieldcal.pipeline, fieldcal.field.adjustment, fieldcal.field.from_images\n"
            "import fieldcal.field.check_points, fieldcal.solver.lsq\n"
            "print(sorted(k for k in ('scipy.stats', 'scipy.optimize') if k in sys.modules))\n")
    assert _printed_by_a_fresh_interpreter(code) == "[]"


def _printed_by_a_fresh_interpreter(code: str) -> str:
    """What ``code`` prints when run by a new Python process in the checkout (its own imports)."""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, check=True)
    return out.stdout.strip()


def _graph():
    mods = dict(_modules(LIBRARY, "fieldcal"))
    graph = {m: set() for m in mods}
    for m, path in mods.items():
        for target, names, _ in _imports(m, path):
            for cand in [f"{target}.{n}" for n in names] + [target]:
                if cand in mods and cand != m:
                    graph[m].add(cand)
                    break
    return graph


def _cycles(graph):
    """Strongly connected components with more than one module (Tarjan)."""
    index, low, stack, on, out, counter = {}, {}, [], set(), [], [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in graph[v]:
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
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def layer_of(module: str) -> int:
    """Index in :data:`LAYERS` of the layer that holds ``module`` (longest prefix wins)."""
    best, index = "", None
    for i, (_, names) in enumerate(LAYERS):
        for name in names:
            if (module == name or module.startswith(name + ".")) and len(name) > len(best):
                best, index = name, i
    if index is None:
        raise KeyError(f"{module} is in no layer of LAYERS")
    return index


def _known_modules():
    return dict(_modules(LIBRARY, "fieldcal")) | dict(_modules(ROOT / "flows", "flows"))


def test_every_module_has_a_layer():
    assert [m for m in _known_modules() if _layer_or_none(m) is None] == []


def _layer_or_none(module: str):
    try:
        return layer_of(module)
    except KeyError:
        return None


def test_the_architecture_page_draws_every_layer():
    """docs/architecture.md shows each package or module of :data:`LAYERS` (as ``name/`` or
    ``name.py``), so the page cannot fall behind the table."""
    page = (ROOT / "docs" / "architecture.md").read_text()
    mods = _known_modules()
    missing = []
    for _, names in LAYERS:
        for name in names:
            if name == "fieldcal":
                continue
            short = name.split(".")[-1]
            shown = f"{short}/" if (name + ".__init__") in mods or any(m.startswith(name + ".") for m in mods) \
                else f"{short}.py"
            if shown not in page:
                missing.append(shown)
    assert missing == []


def test_every_import_points_down_or_sideways():
    """Module-level and deferred imports (inside functions) alike, in fieldcal/ and flows/."""
    mods = _known_modules()
    upward = []
    for m, path in mods.items():
        for target, names, line in _imports(m, path):
            if not target.startswith(("fieldcal", "flows")):
                continue
            imported = next((c for c in [f"{target}.{n}" for n in names] + [target] if c in mods), target)
            if layer_of(imported) > layer_of(m):
                upward.append(f"{path.relative_to(ROOT)}:{line}: {LAYERS[layer_of(m)][0]} imports "
                              f"{imported} ({LAYERS[layer_of(imported)][0]})")
    assert upward == []


def test_no_cycles_between_packages():
    """The subpackages (and top-level modules) of fieldcal, one node each: sideways imports
    within a layer never close a loop either (issue 25: they all reached each other)."""
    def unit(m):
        return ".".join(m.split(".")[:2])

    graph = {}
    for m, targets in _graph().items():
        graph.setdefault(unit(m), set()).update(unit(t) for t in targets if unit(t) != unit(m))
    graph = {u: {t for t in ts if t != "fieldcal"} for u, ts in graph.items()}   # the root: __version__
    assert _cycles(graph) == []


def test_no_import_cycles_in_the_library():
    """Module-level and deferred imports alike: a package's ``__init__`` re-exporting its
    modules counts as importing them."""
    graph = _graph()
    # a package __init__ is imported by every import of its submodules: not an edge back
    for m in graph:
        graph[m] = {t for t in graph[m] if not m.startswith(t + ".")}
    assert _cycles(graph) == []


@pytest.mark.parametrize("top", ["fieldcal", "flows"])
def test_no_private_name_is_imported_from_another_module(top):
    offenders = []
    for m, path in _modules(ROOT / top, top):
        for target, names, line in _imports(m, path):
            if not target.startswith(("fieldcal", "flows")):
                continue
            for n in names:
                if n.startswith("_") and n != "__version__":
                    offenders.append(f"{path.relative_to(ROOT)}:{line}: {n} from {target}")
            if any(p.startswith("_") for p in target.split(".")):
                offenders.append(f"{path.relative_to(ROOT)}:{line}: private module {target}")
    assert offenders == []


@pytest.mark.parametrize("top", ["fieldcal", "flows"])
def test_no_function_is_longer_than_the_limit(top):
    long = []
    for _, path in _modules(ROOT / top, top):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                n = node.end_lineno - node.lineno + 1
                if n > MAX_FUNCTION_LINES:
                    long.append(f"{path.relative_to(ROOT)}:{node.lineno}: {node.name} ({n} lines)")
    assert long == []

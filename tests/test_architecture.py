"""The package's layers, checked on its import statements (every one, including those inside functions).

    base      omnispectral, errors, io, threads, limits, locking,  (import nothing else of the package)
              fingerprint
    core      imaging, spectral                                    (base and each other)
    rig       omnispectral.rig                                     (base, core)
    stages    capture, mosaic                                      (base, core, rig; mosaic never capture)
    product   product                                              (all of the above)
    apps      apps: rendering, relighting, the demo                (all of the above)
    front     view (library), cli (command line)                   (anything; nothing imports cli)

and the simulator (``capture.simulate``, ``capture.scenes``) is used under ``product/`` only by the report's
ground-truth comparison (the demo, which runs it, is an application); ``mosaic`` never sees it.
See docs/architecture.md.
"""

from __future__ import annotations

import ast
import importlib
import re
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / "src"
PACKAGE = "omnispectral"

BASE = {"omnispectral", "omnispectral.errors", "omnispectral.io", "omnispectral.threads", "omnispectral.limits",
        "omnispectral.locking", "omnispectral.fingerprint"}
CORE = ("imaging", "spectral")
SIMULATOR = ("omnispectral.capture.simulate", "omnispectral.capture.scenes")
#: Modules of ``product`` that may use the simulator: the demo runs it; the report compares with its truth.
SIMULATOR_USERS = {"omnispectral.product.report"}
#: Function-level imports kept lazy on purpose: heavy dependencies a code path needs only sometimes.
LAZY_OK = ("matplotlib", "zarr", "dask", "distributed", "scipy.signal", "numba", "uvicorn", "spectral.io.envi",
           "mitsuba", "drjit", "rawpy", "xarray",
           "omnispectral.capture.drivers.gentl")  # the last loads harvesters/genicam and the GenTL native libraries
#: Modules whose function-level imports are not checked (none left: product.align and product.rigcal no
#: longer call each other, session 5).
LAZY_EXEMPT: set[str] = set()


def _module_name(path: Path) -> str:
    parts = path.relative_to(SRC).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imports(path: Path) -> list[tuple[str, bool, int]]:
    """``(imported module, inside a function, line)`` for every import statement of a file."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    module = _module_name(path)
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    out: list[tuple[str, bool, int]] = []

    def visit(node: ast.AST, in_function: bool) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.Import):
                out.extend((a.name, in_function, child.lineno) for a in child.names)
            elif isinstance(child, ast.ImportFrom):
                if child.level:
                    base = package.split(".")[: len(package.split(".")) - child.level + 1]
                    name = ".".join(base + ([child.module] if child.module else []))
                else:
                    name = child.module or ""
                out.append((name, in_function, child.lineno))
                if child.level == 0 and name.startswith(PACKAGE):  # `from pkg import submodule`
                    out.extend((f"{name}.{a.name}", in_function, child.lineno) for a in child.names
                               if (SRC / Path(*f"{name}.{a.name}".split("."))).with_suffix(".py").exists()
                               or (SRC / Path(*f"{name}.{a.name}".split("."))).is_dir())
            visit(child, in_function or isinstance(child, ast.FunctionDef | ast.AsyncFunctionDef))

    visit(tree, False)
    return out


GRAPH = {_module_name(p): _imports(p) for p in sorted((SRC / PACKAGE).rglob("*.py"))}


def _layer(module: str) -> str:
    if module in BASE:
        return "base"
    if module == "omnispectral.__main__":  # ``python -m omnispectral``: the CLI's entry point
        return "cli"
    if module == "omnispectral.rig":
        return "rig"
    return module.split(".")[1]


ALLOWED = {
    "base": {"base"},
    "imaging": {"base", "imaging", "spectral"},
    "spectral": {"base", "imaging", "spectral"},
    "rig": {"base", "imaging", "spectral", "rig"},
    "capture": {"base", "imaging", "spectral", "rig", "capture"},
    "mosaic": {"base", "imaging", "spectral", "rig", "mosaic"},
    "product": {"base", "imaging", "spectral", "rig", "capture", "mosaic", "product"},
    "apps": {"base", "imaging", "spectral", "rig", "capture", "mosaic", "product", "apps"},
    "view": {"base", "imaging", "spectral", "rig", "capture", "mosaic", "product", "apps", "view"},
    "cli": {"base", "imaging", "spectral", "rig", "capture", "mosaic", "product", "apps", "view", "cli"},
}


def _internal(module: str) -> list[tuple[str, int]]:
    return [(name, line) for name, _, line in GRAPH[module] if name == PACKAGE or name.startswith(PACKAGE + ".")]


def test_the_walk_sees_the_package():
    """The check is not vacuous: it finds the modules and their known imports."""
    assert len(GRAPH) > 60
    assert any(name == "omnispectral.product.layout" for name, _ in _internal("omnispectral.product.spectra"))
    assert any(name == "omnispectral.capture.simulate" for name, _ in _internal("omnispectral.apps.demo"))
    assert {_layer(m) for m in GRAPH} == set(ALLOWED)


@pytest.mark.parametrize("module", sorted(GRAPH))
def test_imports_follow_the_layers(module):
    layer = _layer(module)
    bad = [f"line {line}: {name}" for name, line in _internal(module)
           if _layer(name) not in ALLOWED[layer] and name != module]
    assert not bad, f"{module} ({layer}) imports across the layers: {bad}"


def test_nothing_imports_the_cli():
    bad = [(m, name) for m in GRAPH if _layer(m) != "cli"
           for name, _ in _internal(m) if name.startswith("omnispectral.cli")]
    assert not bad


def test_mosaic_and_product_do_not_use_the_simulator():
    bad = [(m, name) for m in GRAPH if m.startswith(("omnispectral.mosaic", "omnispectral.product"))
           and m not in SIMULATOR_USERS for name, _ in _internal(m) if name.startswith(SIMULATOR)]
    assert not bad


def test_mosaic_never_reads_a_rig_or_a_session():
    bad = [(m, name) for m in GRAPH if m.startswith("omnispectral.mosaic")
           for name, _ in _internal(m) if name.startswith(("omnispectral.capture", "omnispectral.rig"))]
    assert not bad


def test_imports_inside_functions_are_only_the_lazy_heavy_ones():
    bad = [(m, line, name) for m, imports in GRAPH.items() if m not in LAZY_EXEMPT
           for name, inside, line in imports
           if inside and not any(name == lazy or name.startswith(lazy + ".") for lazy in LAZY_OK)]
    assert not bad, f"imports inside functions (move them to the module top): {bad}"


def test_no_import_cycles_between_modules():
    """No cycle among the package's modules (so no module needs an import hidden in a function)."""
    edges = {m: {n for n, _ in _internal(m) if n in GRAPH and n != m and not m.startswith(n + ".")}
             for m in GRAPH}
    state: dict[str, int] = {}
    cycle: list[str] = []

    def visit(m: str, path: list[str]) -> bool:
        state[m] = 1
        for n in sorted(edges[m]):
            if state.get(n) == 1:
                cycle.extend([*path[path.index(n):], n] if n in path else [m, n])
                return True
            if n not in state and visit(n, [*path, n]):
                return True
        state[m] = 2
        return False

    for m in sorted(GRAPH):
        if m not in state and visit(m, [m]):
            break
    assert not cycle, " -> ".join(cycle)


def test_the_paper_table_names_functions_that_exist():
    """docs/architecture.md opens with a table from the paper's equations and figures to the code: every
    fully qualified name in it must resolve (so a move or rename cannot leave it pointing nowhere)."""
    doc = (SRC.parent / "docs" / "architecture.md").read_text(encoding="utf-8")
    table = doc[: doc.index("\n## ")]
    names = sorted(set(re.findall(r"`(omnispectral(?:\.\w+)+)`", table)))
    assert len(names) >= 20
    missing = []
    for name in names:
        parts = name.split(".")
        for cut in range(len(parts), 0, -1):  # longest importable module prefix, then attributes
            try:
                obj = importlib.import_module(".".join(parts[:cut]))
            except ImportError:
                continue
            try:
                for attr in parts[cut:]:
                    obj = getattr(obj, attr)
            except AttributeError:
                missing.append(name)
            break
    assert not missing, missing

"""The package's layers, checked on its import statements (every one, including those inside functions).

    base      omnispectral, errors, io, threads, limits, locking,  (import nothing else of the package)
              fingerprint, ownership, extras, progress, choices, checksums, filebytes
    core      imaging → spectral                                   (base; imaging may use spectral, never the reverse)
    rig       omnispectral.rig                                     (base, core)
    stages    capture (the real path), mosaic                      (base, core, rig; mosaic never capture)
    product   product                                              (all of the above)
    apps      apps: rendering, relighting, the demo                (all of the above)
    sim       the simulator                                        (base, core, rig, stages)
    front     view (library), cli (command line)                   (anything; nothing imports cli)

Only ``sim`` itself, the demo (``apps.demo``), the command line and the tests import the simulator: processing,
the capture path, the other applications and the viewer never see it.  See docs/architecture.md.
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
        "omnispectral.locking", "omnispectral.fingerprint", "omnispectral.ownership", "omnispectral.extras",
        "omnispectral.checksums", "omnispectral.compiled", "omnispectral.allocator", "omnispectral.filebytes",
        "omnispectral.progress",
        "omnispectral.choices"}  # names and defaults the command line shows: its parsers import nothing heavy
SIMULATOR = "omnispectral.sim"
#: Modules outside ``sim`` that may import it: the demo runs a simulation; the command line offers it.
SIMULATOR_USERS = ("omnispectral.apps.demo", "omnispectral.cli", "omnispectral.__main__")
#: Function-level imports kept lazy on purpose: heavy dependencies a code path needs only sometimes.
LAZY_OK = ("matplotlib", "zarr", "dask", "distributed", "scipy.signal", "numba", "uvicorn", "spectral.io.envi",
           "mitsuba", "drjit", "rawpy", "xarray",
           "omnispectral.capture.drivers.gentl")  # the last loads harvesters/genicam and the GenTL native libraries
#: Modules whose function-level imports are not checked.
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
    "spectral": {"base", "spectral"},
    "rig": {"base", "imaging", "spectral", "rig"},
    "capture": {"base", "imaging", "spectral", "rig", "capture"},
    "mosaic": {"base", "imaging", "spectral", "rig", "mosaic"},
    "product": {"base", "imaging", "spectral", "rig", "capture", "mosaic", "product"},
    "apps": {"base", "imaging", "spectral", "rig", "capture", "mosaic", "product", "apps", "sim"},
    "sim": {"base", "imaging", "spectral", "rig", "capture", "mosaic", "sim"},
    "view": {"base", "imaging", "spectral", "rig", "capture", "mosaic", "product", "apps", "view"},
    "cli": {"base", "imaging", "spectral", "rig", "capture", "mosaic", "product", "apps", "sim", "view", "cli"},
}


def _internal(module: str) -> list[tuple[str, int]]:
    return [(name, line) for name, _, line in GRAPH[module] if name == PACKAGE or name.startswith(PACKAGE + ".")]


def test_the_walk_sees_the_package():
    """The check is not vacuous: it finds the modules and their known imports."""
    assert len(GRAPH) > 60
    assert any(name == "omnispectral.product.layout" for name, _ in _internal("omnispectral.product.spectra"))
    assert any(name == "omnispectral.sim.simulate" for name, _ in _internal("omnispectral.apps.demo"))
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


def test_only_the_demo_and_the_cli_use_the_simulator():
    """Processing, the capture path, the applications and the viewer never import ``omnispectral.sim``."""
    users = {m for m in GRAPH if any(n == SIMULATOR or n.startswith(SIMULATOR + ".") for n, _ in _internal(m))}
    assert "omnispectral.apps.demo" in users and "omnispectral.cli.simulate" in users  # the check is not vacuous
    bad = sorted(m for m in users if not (m == SIMULATOR or m.startswith((SIMULATOR + ".", *SIMULATOR_USERS))))
    assert not bad, f"import the simulator: {bad}"


def test_the_capture_package_is_the_real_path_only():
    """Nothing under ``capture/`` simulates: no module there defines a simulated device or renders a scene."""
    simulating = re.compile(r"^class (Simulated|Fake)\w*|^def simulate(_\w+)?\(", re.M)
    offenders = [str(p.relative_to(SRC)) for p in sorted((SRC / PACKAGE / "capture").rglob("*.py"))
                 if simulating.search(p.read_text(encoding="utf-8"))]
    assert not offenders


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


def _references() -> dict[str, set[str]]:
    """Identifier → the modules whose code refers to it (a name, an attribute or a keyword argument's value),
    definitions left out."""
    refs: dict[str, set[str]] = {}
    for path in sorted((SRC / PACKAGE).rglob("*.py")):
        module = _module_name(path)
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Name):
                refs.setdefault(node.id, set()).add(module)
            elif isinstance(node, ast.Attribute):
                refs.setdefault(node.attr, set()).add(module)
            elif isinstance(node, ast.ImportFrom):  # a re-export is not a use: counted only with a use
                continue
    return refs


def test_the_paper_table_names_what_the_pipeline_runs():
    """Every function or class the paper table names is used by the package's own code outside the simulator
    (the pipeline, the command line, the apps): nothing in the table is reached only from the tests.  Names of
    the simulator (a simulated scene as the ground truth of an application) are used within it."""
    doc = (SRC.parent / "docs" / "architecture.md").read_text(encoding="utf-8")
    names = sorted(set(re.findall(r"`(omnispectral(?:\.\w+)+)`", doc[: doc.index("\n## ")])))
    refs = _references()
    unused = []
    for name in names:
        last = name.rsplit(".", 1)[1]
        if (SRC / Path(*name.split("."))).with_suffix(".py").exists() or (SRC / Path(*name.split("."))).is_dir():
            continue  # a module
        users = refs.get(last, set())
        in_sim = name.startswith(SIMULATOR + ".")
        if not any(u.startswith(SIMULATOR) == in_sim or (not in_sim and u.startswith("omnispectral.cli"))
                   for u in users):
            unused.append(name)
    assert not unused, f"named in the paper table but used by no pipeline code: {unused}"


def test_every_module_declares_its_public_names():
    """Each module says what it offers (``__all__``), and every name it lists exists there."""
    missing, wrong = [], []
    for path in sorted((SRC / PACKAGE).rglob("*.py")):
        if path.name in ("__init__.py", "__main__.py"):
            continue
        module = _module_name(path)
        tree = ast.parse(path.read_text(encoding="utf-8"))
        listed = next((n.value for n in tree.body if isinstance(n, ast.Assign)
                       and any(isinstance(t, ast.Name) and t.id == "__all__" for t in n.targets)), None)
        if listed is None:
            missing.append(module)
            continue
        targets = [t for n in tree.body if isinstance(n, ast.Assign) for t in n.targets]
        names = [e for t in targets for e in (t.elts if isinstance(t, ast.Tuple) else [t])]
        defined = {e.id for e in names if isinstance(e, ast.Name)}
        defined |= {n.target.id for n in tree.body if isinstance(n, ast.AnnAssign) and isinstance(n.target, ast.Name)}
        defined |= {n.name for n in tree.body if isinstance(n, ast.FunctionDef | ast.AsyncFunctionDef | ast.ClassDef)}
        defined |= {(a.asname or a.name).split(".")[0] for n in tree.body if isinstance(n, ast.Import | ast.ImportFrom)
                    for a in n.names}
        wrong += [f"{module}.{e.value}" for e in listed.elts if e.value not in defined]
    assert not missing, f"no __all__: {missing}"
    assert not wrong, f"listed in __all__ but not defined: {wrong}"


def _documented_entry_points() -> list[str]:
    """Every ``omnispectral.…`` name of the paper table and of README (its code and its imports)."""
    doc = (SRC.parent / "docs" / "architecture.md").read_text(encoding="utf-8")
    readme = (SRC.parent / "README.md").read_text(encoding="utf-8")
    names = set(re.findall(r"`(omnispectral(?:\.\w+)+)`", doc[: doc.index("\n## ")]))
    names |= set(re.findall(r"`(omnispectral(?:\.\w+)+)`", readme))
    for module, listed in re.findall(r"from (omnispectral[.\w]*) import \(?([\w, ]+)", readme):
        names |= {f"{module}.{n.strip()}" for n in listed.split(",") if n.strip()}
    return sorted(names)


def test_every_documented_entry_point_has_numpydoc_sections_and_a_citation():
    """Functions and classes the paper table or README names document their Parameters (and, for functions,
    Returns) in numpydoc form and cite their source (a References section)."""
    import inspect

    lacking = {}
    for name in _documented_entry_points():
        parts = name.split(".")
        obj = None
        for cut in range(len(parts), 0, -1):
            try:
                obj = importlib.import_module(".".join(parts[:cut]))
            except ImportError:
                continue
            for attr in parts[cut:]:
                obj = getattr(obj, attr, None)
            break
        if obj is None or inspect.ismodule(obj) or not callable(obj):
            continue
        doc = inspect.getdoc(obj) or ""
        wanted = ("Parameters", "References") if inspect.isclass(obj) else ("Parameters", "Returns", "References")
        missing = [s for s in wanted if not re.search(rf"^{s}\n-+$", doc, re.M)]
        if missing:
            lacking[name] = missing
    assert len(_documented_entry_points()) >= 40
    assert not lacking, lacking


def test_freed_arrays_are_reused_without_page_faults():
    """After reuse_freed_memory, new threads that hold and free a bracket of frame-sized arrays reuse the memory
    other threads freed instead of faulting fresh pages in (glibc; elsewhere the function says it did nothing).
    Without it, this pattern faults in ~19000 pages here; with it, ~4000."""
    import subprocess
    import sys

    code = """if True:
        import resource, threading
        import numpy as np
        from omnispectral.allocator import reuse_freed_memory
        applied = reuse_freed_memory()
        def work():
            for _ in range(4):
                held = [np.ones(13 * 2**20 // 8) for _ in range(10)]  # a bracket's frames, held, then freed
                del held
        warm = threading.Thread(target=work)  # the process's memory grows once
        warm.start()
        warm.join()
        before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
        threads = [threading.Thread(target=work) for _ in range(2)]  # new threads, as each stage starts its own
        for t in threads: t.start()
        for t in threads: t.join()
        print(applied, resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
        """
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split()
    if out[0] != "True":
        pytest.skip("not glibc: the allocator is left alone")
    pages = 13 * 2**20 // 4096
    assert int(out[1]) < 3 * pages, out  # 80 arrays of 3328 pages each: 266240 pages with no reuse at all

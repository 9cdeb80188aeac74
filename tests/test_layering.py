"""Import contracts: which package may import which (function-local imports counted), no cycles; a pure core.

Every package (and top-level module) of ``mntes_stream`` declares in
:data:`CONTRACTS` the packages it may import; ``errors`` and the root
package (``__version__``) are open to all. An import anywhere in a module,
inside a function too, counts. The contracts form no cycle, and the code
keeps them. Between modules: no new import cycle, and no module imports
another's private names; what is still to fix is listed
(:data:`KNOWN_MODULE_CYCLES`, :data:`KNOWN_PRIVATE_IMPORTS`), each entry
required to still occur, so a fixed one leaves its list.
docs/architecture.md "Layers".
"""

from __future__ import annotations

import ast
import graphlib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
CORE = ROOT / "mntes_stream" / "core"
EDGE_PACKAGES = [
    "mntes_stream." + p.stem if p.suffix == ".py" else "mntes_stream." + p.name
    for p in (ROOT / "mntes_stream").iterdir()
    if p.name not in ("core", "errors.py", "__init__.py", "__main__.py", "__pycache__", "schemas", "py.typed")
    and (p.suffix == ".py" or (p / "__init__.py").exists())
]
FORBIDDEN_MODULES = {
    "zenoh", "mcap", "msgpack", "matplotlib", "h5py", "tomllib", "tomli_w", "socket", "subprocess",
    "pickle", "shutil", "pathlib", "io", "multiprocessing", "concurrent", "threading", "aiohttp", "plotly", "selenium", "sqlite3", "urllib", "http",
    *EDGE_PACKAGES,
}
FORBIDDEN_CALLS = {"open", "print", "input", "__import__"}
FORBIDDEN_ATTRS = {
    "read_text", "write_text", "read_bytes", "write_bytes", "savefig", "open", "save", "savez",
    "savez_compressed", "load", "loadtxt", "savetxt", "genfromtxt", "tofile", "fromfile", "import_module",
    "system", "popen", "remove", "unlink", "makedirs", "mkdir",
}


def _resolve(module: str | None, level: int, package: str) -> str:
    """Absolute module name of an ``ImportFrom`` (relative imports included)."""
    if level == 0:
        return module or ""
    base = package.split(".")[: len(package.split(".")) - (level - 1)]
    return ".".join(base + ([module] if module else []))


def _imports(tree, package: str):
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield alias.name
        elif isinstance(node, ast.ImportFrom):
            base = _resolve(node.module, node.level, package)
            yield base
            for alias in node.names:  # `from .. import plots` imports a module, not a name
                yield f"{base}.{alias.name}"


def _problems(path: Path, package: str) -> list[str]:
    tree = ast.parse(path.read_text())
    out = []
    for name in _imports(tree, package):
        if any(name == m or name.startswith(m + ".") for m in FORBIDDEN_MODULES):
            out.append(f"{path.name} imports {name}")
    for node in ast.walk(tree):
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id in FORBIDDEN_CALLS:
            out.append(f"{path.name}:{node.lineno} calls {node.func.id}()")
        if isinstance(node, ast.Attribute) and node.attr in FORBIDDEN_ATTRS:
            out.append(f"{path.name}:{node.lineno} uses .{node.attr}")
    return out


def test_core_imports_no_edges_and_does_no_io():
    files = sorted(CORE.rglob("*.py"))
    assert len(files) >= 10
    assert "mntes_stream.service" in EDGE_PACKAGES and "mntes_stream.io" in EDGE_PACKAGES
    problems = []
    for f in files:
        rel = f.relative_to(ROOT).with_suffix("")
        package = ".".join(rel.parts[:-1])
        problems += _problems(f, package)
    assert not problems, problems


@pytest.mark.parametrize(
    "source, expected",
    [
        ("from ..io import codec\n", "imports mntes_stream.io"),
        ("from .. import reports\n", "imports mntes_stream.reports"),
        ("from ..reports import plots\n", "imports mntes_stream.reports.plots"),
        ("import zenoh\n", "imports zenoh"),
        ("def f(p):\n    return p.open()\n", "uses .open"),
        ("import numpy as np\nnp.save('x', 1)\n", "uses .save"),
        ("import importlib\nimportlib.import_module('zenoh')\n", "uses .import_module"),
        ("from pathlib import Path\n", "imports pathlib"),
    ],
)
def test_the_checker_catches_disguised_edges(tmp_path, source, expected):
    f = tmp_path / "mod.py"
    f.write_text(source)
    assert any(expected in p for p in _problems(f, "mntes_stream.core"))


# ---------------------------------------------------------------------------------------------- import contracts

PACKAGE = ROOT / "mntes_stream"
OPEN_TO_ALL = {"errors", "mntes_stream"}
_SERVICE_PLUGIN = {"core", "io", "service"}  # packages whose services build on service.base
CONTRACTS: dict[str, set[str]] = {
    "core": set(),
    "io": {"core"},
    "options": {"core", "io"},  # command-line options shared by cli/ and bench/
    "reports": {"core", "io"},
    "foxglove": {"core", "io"},  # json channels; its service is service/foxglove.py
    "pipeline": {"core", "io"},  # the converter without zenoh: live, offline and G3 run it
    "service": {"core", "io", "foxglove", "pipeline"},  # the registry names the services above it as "module:Class"
    "monitor": _SERVICE_PLUGIN | {"pipeline"},  # its shadow: a linear ConverterPipeline
    "dfmux": _SERVICE_PLUGIN | {"g3"},  # board housekeeping: the G3 path's wiring and bias (g3.mapping)
    "g3": _SERVICE_PLUGIN | {"pipeline"},  # OpticalPower and convert RUN.g3 run the pipeline; g3-bridge is a service
    "ocs": _SERVICE_PLUGIN | {"g3"},  # OCS HK files are G3 files: g3.ocs_hkfile, g3.ocs_hk
    "feeds": {"core", "io", "g3"},
    "bench": {"core", "io", "options", "reports", "pipeline", "service", "foxglove", "monitor", "dfmux", "g3", "ocs",
              "feeds"},
    "cli": {"core", "io", "options", "reports", "pipeline", "service", "foxglove", "monitor", "dfmux", "g3", "ocs",
            "feeds", "bench"},
    "__main__": {"cli"},
}
# Cycles between modules of one package (function-local imports counted), still to fix.
KNOWN_MODULE_CYCLES = {
    frozenset({"feeds.frameworks", "feeds.frameworks._common", "feeds.frameworks.litebird_io",
               "feeds.frameworks.sotodlib_io", "feeds.frameworks.toast_io", "feeds.hdf5", "feeds.recorded"}),
}


def _modules() -> dict[str, tuple[Path, str]]:
    """Dotted module name (without ``mntes_stream.``) -> (file, the package its relative imports resolve in)."""
    out = {}
    for f in sorted(PACKAGE.rglob("*.py")):
        parts = f.relative_to(ROOT).with_suffix("").parts
        name = ".".join(parts[1:-1] if parts[-1] == "__init__" else parts[1:]) or "mntes_stream"
        out[name] = (f, ".".join(parts[:-1]))
    return out


def _package_of(dotted: str, known: set[str]) -> str | None:
    """The top-level package of ``mntes_stream.X...`` (``mntes_stream`` for the root's own names), else None."""
    parts = dotted.split(".")
    if parts[0] != "mntes_stream":
        return None
    return parts[1] if len(parts) > 1 and parts[1] in known else "mntes_stream"


def _package_imports(path: Path, package: str, known: set[str]):
    """(line, imported package) for every import of ``mntes_stream`` anywhere in the file."""
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            names = [_resolve(node.module, node.level, package)]
        else:
            continue
        for name in names:
            if (pkg := _package_of(name, known)) is not None:
                yield node.lineno, pkg


def _violations(modules) -> dict[tuple[str, str], list[str]]:
    known = {name.split(".")[0] for name in _modules()} - {"mntes_stream"}
    out: dict[tuple[str, str], list[str]] = {}
    for name, (path, package) in modules.items():
        src = name.split(".")[0]
        for line, dst in _package_imports(path, package, known):
            if dst != src and dst not in OPEN_TO_ALL and dst not in CONTRACTS.get(src, set()):
                out.setdefault((src, dst), []).append(f"{name}:{line}")
    return out


def test_every_package_has_a_contract_and_the_contracts_have_no_cycle():
    packages = {name.split(".")[0] for name in _modules()} - OPEN_TO_ALL
    assert packages == set(CONTRACTS), f"declare these in CONTRACTS: {packages ^ set(CONTRACTS)}"
    graphlib.TopologicalSorter(CONTRACTS).static_order()  # CycleError names the cycle


def test_packages_import_only_what_their_contract_allows():
    found = _violations(_modules())
    assert not found, found


def test_the_g3_converter_runs_the_pipeline_and_only_its_bridge_service_imports_service():
    # OpticalPower and convert RUN.g3 take the converter from pipeline/ (below service/); the g3-bridge is a
    # service (service.base), the one module of g3 that may import service.
    modules = _modules()
    known = {name.split(".")[0] for name in modules} - {"mntes_stream"}
    uses = {name: {pkg for _, pkg in _package_imports(path, package, known)} for name, (path, package) in modules.items()
            if name.split(".")[0] == "g3"}
    assert {name for name, pkgs in uses.items() if "service" in pkgs} == {"g3.bridge"}
    assert "pipeline" in uses["g3.power"] and "pipeline" in uses["g3.files"]


def _module_cycles(modules) -> set[frozenset[str]]:
    """Strongly connected groups (> 1 module) of the import graph between modules, any import counted.

    Each name imported is an edge to the module that holds it: ``from pkg import a, b`` gives two when both
    are modules, and a name of a package's ``__init__`` (``from mntes_stream.g3 import spt3g`` in ``g3.power``)
    is an edge to that ``__init__``, its own parent package's too.
    """
    graph: dict[str, set[str]] = {name: set() for name in modules}
    for name, (path, package) in modules.items():
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = _resolve(node.module, node.level, package)
                targets = [f"{base}.{a.name}" for a in node.names]
            else:
                continue
            for t in targets:
                t = t.removeprefix("mntes_stream.")
                while t and t not in modules:
                    t = t.rpartition(".")[0]
                if t and t != name:
                    graph[name].add(t)
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    groups = set()

    def visit(v):  # Tarjan
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            group = set()
            while (w := stack.pop()) != v:
                group.add(w)
            if group:
                groups.add(frozenset(group | {v}))

    for v in graph:
        if v not in index:
            visit(v)
    return groups


def test_no_new_import_cycle_between_modules():
    found = _module_cycles(_modules())
    assert not found - KNOWN_MODULE_CYCLES, sorted(map(sorted, found - KNOWN_MODULE_CYCLES))
    assert not KNOWN_MODULE_CYCLES - found, f"fixed, remove from KNOWN_MODULE_CYCLES: {KNOWN_MODULE_CYCLES - found}"


# Private names other modules still import (``from m import _name``); a package's private *modules* are fine
# within the package. Still to fix; each must still occur.
KNOWN_PRIVATE_IMPORTS = {
    "service.recorder -> io.transport._named_paths",
}


def _private_imports(modules) -> set[str]:
    """``importer -> module._name`` for each private name imported from another module."""
    out = set()
    for name, (path, package) in modules.items():
        for node in ast.walk(ast.parse(path.read_text())):
            if not isinstance(node, ast.ImportFrom):
                continue
            base = _resolve(node.module, node.level, package).removeprefix("mntes_stream").lstrip(".")
            for alias in node.names:
                target = f"{base}.{alias.name}".lstrip(".")
                if not alias.name.startswith("_") or alias.name.startswith("__") or base == name:
                    continue
                if target in modules and target.split(".")[0] == name.split(".")[0]:
                    continue  # a private module of the importer's own package
                out.add(f"{name} -> {target}")
    return out


def test_no_module_imports_another_modules_private_names():
    found = _private_imports(_modules())
    assert not found - KNOWN_PRIVATE_IMPORTS, sorted(found - KNOWN_PRIVATE_IMPORTS)
    assert not KNOWN_PRIVATE_IMPORTS - found, f"fixed, remove from KNOWN_PRIVATE_IMPORTS: {KNOWN_PRIVATE_IMPORTS - found}"


def test_the_private_name_checker(tmp_path):
    f = tmp_path / "m.py"
    f.write_text("def f():\n    from mntes_stream.g3.files import _x\n    from ..io import _codec\n"
                 "    from . import _kernels\n")
    assert _private_imports({"service.m": (f, "mntes_stream.service")}) == {
        "service.m -> g3.files._x", "service.m -> io._codec", "service.m -> service._kernels"}


@pytest.mark.parametrize(
    "package, source, edge",
    [
        ("mntes_stream.io", "def f():\n    from mntes_stream.service import base\n", ("io", "service")),
        ("mntes_stream.io", "def f():\n    import mntes_stream.cli._common\n", ("io", "cli")),
        ("mntes_stream.service", "from ..g3 import bridge\n", ("service", "g3")),
        ("mntes_stream.bench", "class B:\n    def m(self):\n        from ..cli import _common\n", ("bench", "cli")),
    ],
)
def test_the_contract_checker_sees_function_local_and_relative_imports(tmp_path, package, source, edge):
    f = tmp_path / "mod.py"
    f.write_text(source)
    name = package.removeprefix("mntes_stream.") + ".mod"
    assert edge in _violations({name: (f, package)})


def test_a_cycle_between_modules_is_found(tmp_path):
    a, b = tmp_path / "a.py", tmp_path / "b.py"
    a.write_text("def f():\n    from mntes_stream.io import b\n")
    b.write_text("from . import a\n")
    assert _module_cycles({"io.a": (a, "mntes_stream.io"), "io.b": (b, "mntes_stream.io")}) == {
        frozenset({"io.a", "io.b"})}


def test_a_submodule_importing_its_own_package_back_is_a_cycle(tmp_path):
    # The loop g3/__init__ <-> g3.power had: __init__ imports the submodule (lazily), which takes a name of __init__.
    init, power, mapping = tmp_path / "__init__.py", tmp_path / "power.py", tmp_path / "mapping.py"
    init.write_text("def __getattr__(name):\n    from mntes_stream.g3.power import OpticalPower\n")
    power.write_text("from mntes_stream.g3 import spt3g\nfrom . import mapping\n")
    mapping.write_text("import numpy\n")
    modules = {"g3": (init, "mntes_stream.g3"), "g3.power": (power, "mntes_stream.g3"),
               "g3.mapping": (mapping, "mntes_stream.g3")}
    assert _module_cycles(modules) == {frozenset({"g3", "g3.power"})}
    runtime = tmp_path / "runtime.py"
    runtime.write_text("import sys\n")
    power.write_text("from mntes_stream.g3.runtime import spt3g\nfrom . import mapping\n")  # not through __init__
    assert _module_cycles(modules | {"g3.runtime": (runtime, "mntes_stream.g3")}) == set()


def test_every_registry_entry_is_a_service_under_its_own_name():
    from mntes_stream.service.base import Service
    from mntes_stream.service.registry import ENTRIES, SERVICES

    assert len(ENTRIES) >= 11
    for name in ENTRIES:
        cls = SERVICES[name]
        assert issubclass(cls, Service) and cls.name == name, (name, cls)

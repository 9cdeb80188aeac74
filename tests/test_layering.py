"""The core is pure computation: it never imports the edges nor does I/O."""

from __future__ import annotations

import ast
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


def test_edge_modules_stay_small():
    """No module in service/ or io/ over 500 lines: one concern each (split a package instead)."""
    files = [p for d in ("service", "io") for p in (ROOT / "mntes_stream" / d).rglob("*.py")]
    assert len(files) >= 10
    big = {str(p.relative_to(ROOT)): n for p in files if (n := len(p.read_text().splitlines())) > 500}
    assert not big, big

"""The core is pure computation: it never imports the edges nor does I/O."""

from __future__ import annotations

import ast
from pathlib import Path

CORE = Path(__file__).resolve().parents[1] / "mntes_stream" / "core"
FORBIDDEN_MODULES = {"zenoh", "mcap", "msgpack", "matplotlib", "h5py", "tomllib", "tomli_w", "socket",
                     "subprocess", "mntes_stream.io", "mntes_stream.cli", "mntes_stream.plots",
                     "mntes_stream.services", "mntes_stream.transport"}
FORBIDDEN_CALLS = {"open", "print", "input"}


def _imports(tree):
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield alias.name
        elif isinstance(node, ast.ImportFrom) and node.module:
            yield node.module


def test_core_imports_no_edges_and_does_no_io():
    files = sorted(CORE.rglob("*.py"))
    assert len(files) >= 5
    problems = []
    for f in files:
        tree = ast.parse(f.read_text())
        for name in _imports(tree):
            if any(name == m or name.startswith(m + ".") for m in FORBIDDEN_MODULES):
                problems.append(f"{f.name} imports {name}")
        for node in ast.walk(tree):
            if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id in FORBIDDEN_CALLS:
                problems.append(f"{f.name}:{node.lineno} calls {node.func.id}()")
            if isinstance(node, ast.Attribute) and node.attr in {"read_text", "write_text", "read_bytes", "write_bytes", "savefig"}:
                problems.append(f"{f.name}:{node.lineno} uses .{node.attr}")
    assert not problems, problems

"""The user's cache: bounded by size (least recently used out first), outside the package, shown and cleared."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

from mntes_stream.core.params import table1_params
from mntes_stream.io.cache import prune, usage
from mntes_stream.pipeline.build import cached_bank

ROOT = Path(__file__).resolve().parents[1]


def _params(i: int) -> dict:
    p = table1_params(f"b0m0c{i:03d}", r_n_ohm=1.0 + 0.01 * i)
    return {p.detector_id: p}


def test_the_table_cache_keeps_to_its_cap_dropping_the_least_recently_used(tmp_path):
    one = cached_bank("table", _params(0), str(tmp_path))
    size = next(tmp_path.glob("*.npz")).stat().st_size
    # Room for two entries: the third write removes the least recently used, not the newest nor a just-loaded one.
    cap_mb = 2.5 * size / 1e6
    first = next(tmp_path.glob("*.npz"))
    os.utime(first, (time.time() - 100, time.time() - 100))
    cached_bank("table", _params(1), str(tmp_path), cap_mb)
    second = next(p for p in tmp_path.glob("*.npz") if p != first)
    os.utime(second, (time.time() - 50, time.time() - 50))
    again = cached_bank("table", _params(0), str(tmp_path), cap_mb)  # a hit: touched, so now the most recently used
    assert again.identity == one.identity and first.stat().st_mtime > time.time() - 10
    cached_bank("table", _params(2), str(tmp_path), cap_mb)
    left = sorted(tmp_path.glob("*.npz"))
    assert len(left) == 2 and first in left and second not in left
    assert sum(p.stat().st_size for p in left) <= 2.5 * size


def test_prune_never_removes_what_is_kept_and_ignores_what_is_gone(tmp_path):
    files = []
    for i in range(4):
        f = tmp_path / f"e{i}.npz"
        f.write_bytes(b"x" * 1000)
        os.utime(f, (1000 + i, 1000 + i))
        files.append(f)
    removed = prune(tmp_path, 2500, keep=(files[0],))
    assert removed == files[1:3] and sorted(tmp_path.iterdir()) == [files[0], files[3]]
    assert prune(tmp_path / "missing", 0) == []


def test_compiled_kernels_are_cached_in_the_users_cache_not_in_the_package(tmp_path):
    code = ("import numba, mntes_stream.core._kernels as k, mntes_stream.core._uncertainty_kernel as u;"
            "import mntes_stream.core._baselines as b;"
            "paths = {type(m).__name__: d._cache._cache_path for m in (k, u, b) for d in vars(m).values()"
            " if isinstance(d, numba.core.dispatcher.Dispatcher)};"
            "print(__import__('json').dumps(sorted(set(paths.values()))))")
    env = {**os.environ, "MNTES_STREAM_CACHE": str(tmp_path)}
    env.pop("NUMBA_CACHE_DIR", None)
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120, check=True)
    paths = json.loads(out.stdout)
    assert paths and all(p.startswith(str(tmp_path / "numba")) for p in paths), paths
    # The user's own numba setting wins.
    env["NUMBA_CACHE_DIR"] = str(tmp_path / "own")
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120, check=True)
    assert all(p.startswith(str(tmp_path / "own")) for p in json.loads(out.stdout))


def test_the_cache_command_shows_the_parts_and_clears_them(tmp_path):
    env = {**os.environ, "MNTES_STREAM_CACHE": str(tmp_path)}
    (tmp_path / "tables").mkdir()
    (tmp_path / "tables" / "table-x.npz").write_bytes(b"x" * 3_000_000)
    (tmp_path / "numba").mkdir()
    (tmp_path / "numba" / "k.nbi").write_bytes(b"x" * 1_000_000)
    cmd = [sys.executable, "-m", "mntes_stream", "cache"]
    shown = subprocess.run(cmd + ["--json"], env=env, capture_output=True, text=True, timeout=60, check=True)
    doc = json.loads(shown.stdout)
    assert doc["root"] == str(tmp_path)
    assert {p["name"]: (p["files"], p["bytes"]) for p in doc["parts"]} == {"tables": (1, 3_000_000),
                                                                            "numba": (1, 1_000_000)}
    text = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=60, check=True).stdout
    assert "tables/" in text and "3.0 MB" in text and "4.0 MB" in text
    cleared = subprocess.run(cmd + ["--clear", "tables"], env=env, capture_output=True, text=True, timeout=60)
    assert cleared.returncode == 0 and "3.0 MB freed" in cleared.stdout
    assert {p.name: p.files for p in usage(str(tmp_path))} == {"tables": 0, "numba": 1}

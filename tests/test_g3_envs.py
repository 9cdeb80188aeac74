"""G3 in every environment (issue 25 item 3): spt3g 1.0.2 files whether or not so3g/toast are installed.

The run is written by spt3g 1.0.2 itself (a child process with so3g refused), with DfMux housekeeping:
so3g's bundled spt3g (0.3.dev289) cannot read that ("version (8) than supported (6)"). Each command
runs in its own process, as a user runs it: "g3 extra alone" hides so3g/toast/sotodlib from the child
(a ``sys.meta_path`` blocker, as if not installed), "every extra" leaves the venv as it is.
"""

from __future__ import annotations

import importlib.util
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("spt3g.core", reason="the g3 extra (spt3g) is not installed")

TESTS = Path(__file__).parent
HIDE = ("so3g", "toast", "sotodlib")
# A child that behaves as if so3g, toast and sotodlib were not installed.
ALONE = f"""
import sys
class _Hidden:
    def find_spec(self, name, path=None, target=None):
        if name.partition(".")[0] in {HIDE!r}:
            raise ModuleNotFoundError("No module named " + repr(name))
sys.meta_path.insert(0, _Hidden())
"""
WRITE = ALONE + """
sys.path.insert(0, sys.argv[1])
import test_g3 as t
from pathlib import Path
from mntes_stream.core.params import table1_params
from mntes_stream.io.paramfile import dump_params
import spt3g
d = Path(sys.argv[2])
t.write(t.raw_frames(), d / "raw.g3")
t.write(t.raw_frames(), d / "scans.g3", collate=True)
dump_params([table1_params(n) for n in t.LAYOUT], d / "names.toml")
print(spt3g.__version__, spt3g.core.__file__)
"""
CLI = "\nfrom mntes_stream.cli import main\nsys.exit(main(sys.argv[1:]))\n"


def has(name: str) -> bool:
    return importlib.util.find_spec(name) is not None


def cli(argv, *, alone=False, before="", timeout=120):
    code = (ALONE if alone else "import sys\n") + before + CLI
    return subprocess.run([sys.executable, "-c", code, *map(str, argv)], capture_output=True, text=True,
                          timeout=timeout)


@pytest.fixture(scope="module")
def run_1_0_2(tmp_path_factory):
    d = tmp_path_factory.mktemp("g3_1_0_2")
    p = subprocess.run([sys.executable, "-c", WRITE, str(TESTS), str(d)], capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stderr[-2000:]
    version, where = p.stdout.split()[-2:]
    assert version == "1.0.2" and "so3g" not in where, p.stdout
    return d


def power(path) -> dict:
    from mntes_stream.io.mcap import Session
    from mntes_stream.io.messages import decode

    out = {}
    for m in Session(path).iter_messages():
        if "/power/" in m.topic:
            msg = decode(m.payload)
            out[(m.topic, msg.seq)] = msg.p_opt_w
    return out


@pytest.mark.parametrize("alone", [True, False], ids=["g3-extra-alone", "every-extra"])
def test_a_spt3g_1_0_2_run_with_dfmux_housekeeping_converts(run_1_0_2, tmp_path, alone):
    if not alone and not has("so3g"):
        pytest.skip("so3g is not installed: 'every extra' is the same as 'g3 extra alone' here")
    out = tmp_path / "out.mcap"
    p = cli(["convert", run_1_0_2 / "raw.g3", out, "--params", run_1_0_2 / "names.toml", "-q", "--json"], alone=alone)
    assert p.returncode == 0, p.stderr[-2000:]
    res = json.loads(p.stdout)
    assert res["spt3g"].startswith("spt3g 1.0.2 ("), res["spt3g"]
    assert res["ledger_line"] == "received 8 chunks: converted 8; lost 0 of 8"
    got = power(out)
    assert len(got) == 8 and sum(v.size for v in got.values()) == 8 * 60  # 2 modules x 4 channels x 60 samples
    assert sum(np.isfinite(v).sum() for v in got.values()) > 50  # random counts: many outside the tables' range
    np.savez(tmp_path.parent / f"power_{alone}.npz", **{f"{k[0]}|{k[1]}": v for k, v in got.items()})
    other = tmp_path.parent / f"power_{not alone}.npz"
    if other.exists():  # both environments give the same power, bit for bit
        with np.load(other) as o:
            assert sorted(o.files) == sorted(f"{k[0]}|{k[1]}" for k in got)
            for k, v in got.items():
                np.testing.assert_array_equal(o[f"{k[0]}|{k[1]}"], v)


@pytest.mark.skipif(not has("toast"), reason="the toast extra is not installed")
def test_export_of_a_spt3g_1_0_2_run_to_toast_reads_the_g3_in_a_child(run_1_0_2, tmp_path):
    p = cli(["export", run_1_0_2 / "scans.g3", "--g3-params", run_1_0_2 / "names.toml", "--format", "toast",
             "--out", tmp_path / "tx", "--json"])
    assert p.returncode == 0, p.stderr[-2000:]
    res = json.loads(p.stdout)
    assert res["observations"] == ["lab_b1234m2", "lab_b1234m5"] and res["detector_samples"] == 8 * 60
    assert sorted(f.name for f in (tmp_path / "tx").iterdir()) == ["lab_b1234m2.h5", "lab_b1234m5.h5"]


@pytest.mark.skipif(not has("so3g"), reason="so3g is not installed")
def test_so3g_after_spt3g_1_0_2_is_one_line_not_a_segfault():
    code = "from mntes_stream.g3 import spt3g; spt3g()\nfrom mntes_stream.errors import import_extra\n" \
           "import_extra('toast', 'toast')"
    p = subprocess.run([sys.executable, "-c", "import sys\n" + code], capture_output=True, text=True, timeout=60)
    assert p.returncode == 1 and "MissingExtraError: toast cannot be imported in a process that has loaded spt3g " \
        "1.0.2" in p.stderr, (p.returncode, p.stderr[-1000:])


@pytest.mark.skipif(not has("so3g"), reason="so3g is not installed")
def test_a_process_that_loaded_so3g_first_says_which_spt3g_in_one_line(run_1_0_2, tmp_path):
    p = cli(["convert", run_1_0_2 / "raw.g3", tmp_path / "o.mcap", "--params", run_1_0_2 / "names.toml", "-q"],
            before="import so3g\n")
    assert p.returncode == 2 and "Traceback" not in p.stderr, p.stderr[-2000:]
    line, = [ln for ln in p.stderr.splitlines() if ln.startswith("mntes-stream: error:")]
    assert "so3g's bundled spt3g" in line and "HkChannelInfo" in line

"""The examples run as a user runs them, on one short recording that ``mntes-stream up`` makes.

One ``up`` run (2 modules x 8 channels, 8 s; module scope) is shared by every
example, as ``--session`` (the examples' own ``up`` call is the same
command). The simulator puts one saturated and one latched channel in each
module; the examples keep a detector only when its power is usable at least
half the time (``examples/_record.py``), and the count they drop is read
from the recording itself. Bad input ends in one line and exit code 2.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
pytestmark = pytest.mark.slow  # processes end to end (CI runs it; the fast subset does not)


def _run(script: str, *args: str, rc: int = 0) -> subprocess.CompletedProcess:
    res = subprocess.run([sys.executable, str(EXAMPLES / script), *args], capture_output=True, text=True,
                         timeout=300)
    assert res.returncode == rc, res.stderr[-3000:]
    return res


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    """The directory of MCAP files a short ``up`` run wrote."""
    work = tmp_path_factory.mktemp("examples")
    res = subprocess.run([sys.executable, "-m", "mntes_stream", "up", "--duration", "8", "--modules", "2",
                          "--channels", "8", "--out", str(work / "up"), "-q"], capture_output=True, text=True,
                         timeout=300)
    assert res.returncode == 0, res.stderr[-3000:]
    rec = work / "up" / "recordings"
    assert list(rec.glob("*.mcap")), res.stdout
    return rec


@pytest.fixture(scope="module")
def dropped(recording):
    """Detectors of the recording usable less than half the time (what the examples leave out)."""
    from mntes_stream.core import flags as fl
    from mntes_stream.feeds import RecordedPower

    usable = np.concatenate([(b.flags & fl.UNUSABLE) == 0 for b in RecordedPower(recording).read().values()])
    assert usable.shape[0] == 16
    n = int((usable.mean(axis=1) < 0.5).sum())
    assert 4 <= n < 16, f"{n} of 16 detectors usable less than half the time (the simulator makes 4 such)"
    return n


def _example(script, recording, tmp_path) -> dict:
    return json.loads(_run(script, "--work", str(tmp_path), "--session", str(recording), "--json").stdout)


def test_toast_example_estimates_spectra(recording, dropped, tmp_path):
    pytest.importorskip("toast", reason="the toast extra is not installed")
    out = _example("toast_noise_psd.py", recording, tmp_path)
    assert out["observations"] == ["lab_b0m0", "lab_b0m1"] and out["detectors"] == 16
    assert out["signal_units"] == "W" and out["sample_rate_hz"] == 152.587890625
    assert out["psd_files"] >= 16 - dropped, out  # TOAST skips only detectors flagged invalid as a whole
    assert out["finite_spectra"] >= 1, out
    assert 1e-19 < out["white_noise_w_per_rthz_median"] < 1e-15


def test_sotodlib_example_drops_mostly_unusable_detectors(recording, dropped, tmp_path):
    pytest.importorskip("sotodlib.core", reason="the sotodlib extra is not installed")
    out = _example("sotodlib_psd.py", recording, tmp_path)
    assert out["observations"] == ["lab_b0m0", "lab_b0m1"]
    assert (out["detectors_kept"], out["detectors_cut"]) == (16 - dropped, dropped), out
    assert out["samples_used"] >= 2 * 128 and out["signal_units"] == "W"
    assert 1e-19 < out["white_noise_w_per_rthz_median"] < 1e-15


def test_litebird_example_bins_a_map_in_watts(recording, dropped, tmp_path):
    pytest.importorskip("litebird_sim", reason="the litebird extra is not installed")
    out = _example("litebird_binned_map.py", recording, tmp_path)
    assert (out["detectors_kept"], out["detectors_cut"]) == (16 - dropped, dropped), out
    assert out["units_in_file"] == "W" and out["units_litebird_reports"] == "K_CMB"  # what its loader says
    assert out["pixels_seen"] > 10, out
    assert out["mean_power_w"] == pytest.approx(out["mean_power_w_from_tod"], rel=0.01), out


def test_bin_map_example_maps_the_export(recording, tmp_path):
    h5 = tmp_path / "export.h5"
    subprocess.run([sys.executable, "-m", "mntes_stream", "export", str(recording), "--out", str(h5), "-q"],
                   check=True, capture_output=True, timeout=300)
    out = json.loads(_run("bin_map.py", str(h5), "--obs", "lab_b0m1", "--json").stdout)
    assert out["observation"] == "lab_b0m1" and out["units"] == "W" and out["hit_pixels"] > 10
    assert 1e-14 < out["map_mean_w"] < 1e-11
    res = _run("bin_map.py", str(h5), "--obs", "lab_b9m9", rc=2)
    assert res.stderr.strip().splitlines() == [
        f"bin_map.py: error: {h5}: no observation 'lab_b9m9'; it has lab_b0m0, lab_b0m1"]


def test_an_empty_session_is_one_line(tmp_path):
    """A recording with nothing in it (e.g. an `up` that had no time to record): one line, exit code 2."""
    (tmp_path / "empty").mkdir()
    for script in ("toast_noise_psd.py", "sotodlib_psd.py", "litebird_binned_map.py"):
        res = _run(script, "--work", str(tmp_path), "--session", str(tmp_path / "empty"), rc=2)
        assert res.stderr.strip().splitlines() == [
            f"{script}: error: --session {tmp_path / 'empty'}: no MCAP file in it (did `mntes-stream up` record "
            "anything?)"]

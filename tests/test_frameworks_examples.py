"""The framework examples run as a user runs them: record with ``up``, export, load natively, spectrum or map.

The TOAST example records its own session with ``mntes-stream up`` (2 modules
x 8 channels, 4 s); the sotodlib and litebird_sim examples take that
recording with ``--session`` (one ``up`` run for the three, to keep CI short).
The simulator puts one saturated and one latched channel in each module: 4
of 16 detectors have no usable power and must be left out (the count is read
from the recording itself).
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("toast")
pytest.importorskip("sotodlib.core")
pytest.importorskip("litebird_sim")

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def _run(script: str, *args: str) -> dict:
    res = subprocess.run([sys.executable, str(EXAMPLES / script), "--json", *args], capture_output=True, text=True,
                         timeout=300)
    assert res.returncode == 0, res.stderr[-3000:]
    return json.loads(res.stdout)


@pytest.fixture(scope="module")
def toast_run(tmp_path_factory):
    work = tmp_path_factory.mktemp("examples")
    return work, _run("toast_noise_psd.py", "--work", str(work), "--duration", "4")


@pytest.fixture(scope="module")
def dead(toast_run):
    """Detectors of the recording with no usable sample at all."""
    from mntes_stream.core import flags as fl
    from mntes_stream.feeds import RecordedPower

    unusable = np.concatenate([(b.flags & fl.UNUSABLE) != 0
                               for b in RecordedPower(toast_run[0] / "up" / "recordings").read().values()])
    assert unusable.shape[0] == 16
    n = int(unusable.all(axis=1).sum())
    assert 4 <= n < 16, f"{n} of 16 detectors without usable power (the simulator makes 4 such)"
    return n


def test_toast_example_records_with_up_and_estimates_spectra(toast_run, dead):
    work, out = toast_run
    assert list((work / "up" / "recordings").glob("*.mcap"))
    assert out["observations"] == ["lab_b0m0", "lab_b0m1"] and out["detectors"] == 16
    assert out["signal_units"] == "W" and out["sample_rate_hz"] == 152.587890625
    assert out["psd_files"] == 16 - dead, out  # TOAST skips detectors flagged invalid as a whole
    assert out["finite_spectra"] >= 1, out
    assert 1e-19 < out["white_noise_w_per_rthz_median"] < 1e-15


def test_sotodlib_example_cuts_unusable_detectors_and_computes_spectra(toast_run, dead):
    work, _ = toast_run
    out = _run("sotodlib_psd.py", "--work", str(work), "--session", str(work / "up" / "recordings"))
    assert out["observations"] == ["lab_b0m0", "lab_b0m1"]
    assert (out["detectors_kept"], out["detectors_cut"]) == (16 - dead, dead), out
    assert out["signal_units"] == "W" and out["sample_rate_hz"] == 152.587890625
    assert 1e-19 < out["white_noise_w_per_rthz_median"] < 1e-15


def test_litebird_example_bins_a_map_in_watts(toast_run, dead):
    work, _ = toast_run
    out = _run("litebird_binned_map.py", "--work", str(work), "--session", str(work / "up" / "recordings"))
    assert (out["detectors_kept"], out["detectors_cut"]) == (16 - dead, dead), out
    assert out["units_in_file"] == "W" and out["units_litebird_reports"] == "K_CMB"  # what its loader says
    assert out["pixels_seen"] > 10, out
    assert out["mean_power_w"] == pytest.approx(out["mean_power_w_from_tod"], rel=0.01), out

"""Readout noise as a setting (issue 26): the estimator, `mntes-stream noise RUN` on a real MCAP
recording, the noise file and what a noise model makes of it."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from mntes_stream.cli import main
from mntes_stream.core import uncertainty as U
from mntes_stream.errors import ConfigError


def test_white_noise_estimator_removes_drift_glitches_and_quantisation():
    rng = np.random.default_rng(4)
    n = 20_000
    t = np.arange(n) / 152.6
    truth = np.array([0.8, 2.0, 30.0])
    # A wander and a drift, in counts (a line at f leaks (2 pi f / f_s)^2 of its amplitude: 0.03 counts here).
    slow = 2e3 * np.sin(2 * np.pi * 0.1 * t) + 20.0 * t + 1e-3 * t**2
    x = np.rint(1e6 + slow + truth[:, None] * rng.standard_normal((3, n)))
    x[:, ::997] += 1e5  # glitches
    sigma, used = U.white_noise_counts(x)
    np.testing.assert_allclose(sigma, truth, rtol=0.03)
    assert np.all(used > 0.99 * (n - 2))
    # Without removing the rounding, 0.8 counts would read sqrt(0.64 + 1/12) = 0.85.
    assert abs(sigma[0] - 0.8) < abs(math.sqrt(0.64 + 1 / 12) - 0.8)
    short, n_short = U.white_noise_counts(np.zeros((1, 2)))
    assert np.isnan(short[0]) and n_short[0] == 0


def _recording(tmp_path, nei_a_rthz: float, seconds: float = 12.0):
    """A real simulated MCAP recording: 2 modules x 4 channels, readout noise only."""
    from mntes_stream.core.sim import SimConfig
    from mntes_stream.io.paramfile import dump_params
    from mntes_stream.service.simulator import SimulatorSource, write_mcap

    cfg = SimConfig(modules=2, channels=4, nep_w_rthz=0.0, nei_a_rthz=nei_a_rthz, seed=3)
    src = SimulatorSource(cfg, "lab", 0.1)
    path = tmp_path / "dark.mcap"
    write_mcap(src, str(path), seconds)
    dump_params(src.params, tmp_path / "dark.params.toml")
    return path, tmp_path / "dark.params.toml", cfg


def test_noise_command_on_a_recording_and_the_noise_file(tmp_path, capsys):
    nei = 5e-12
    path, params, cfg = _recording(tmp_path, nei)
    expected = nei * math.sqrt(cfg.sample_rate_hz / 2.0)
    out = tmp_path / "noise.json"
    assert main(["noise", str(path), "--params", str(params), "--out", str(out), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc == json.loads(out.read_text())
    assert len(doc["channels"]) == 8 and not doc["without_gain"]
    vals = np.array(list(doc["readout_noise_a"].values()))
    # 12 s at 152.6 Hz: about 1,500 second differences per quadrature, 2% statistical error each.
    np.testing.assert_allclose(vals, expected, rtol=0.08)
    assert abs(np.median(vals) / expected - 1) < 0.03
    assert set(doc["by_module"]) == {"b0m0", "b0m1"}

    from mntes_stream.core.params import table1_params
    from mntes_stream.io.noisefile import load_noise

    measured, source = load_noise(out)
    ids = sorted(doc["readout_noise_a"])
    nm = U.noise_model([table1_params(d) for d in [*ids, "b0m1c099", "b5m5c000"]], measured_a=measured,
                       measured_from=source)
    assert nm.source == ("measured:detector",) * 8 + ("measured:module", "default")
    assert nm.provenance()["readout_noise_measured_from"] == str(out)
    from mntes_stream.io.noisefile import noise_model_for

    nm2 = noise_model_for([table1_params(ids[0])], U.UncertaintySettings(noise_file=str(out)))
    assert nm2.readout_noise_a[0] == doc["readout_noise_a"][ids[0]] and nm2.source == ("measured:detector",)

    # Existing output without --overwrite, a bad duration, a file that is not a noise file: one line, rc 2.
    assert main(["noise", str(path), "--out", str(out), "-q"]) == 2
    assert main(["noise", str(path), "--duration", "0"]) == 2
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"format": "mntes-noise", "version": 1, "readout_noise_a": {"b0m0c000": -1}}))
    with pytest.raises(ConfigError, match="finite number >= 0"):
        load_noise(bad)
    err = capsys.readouterr().err
    assert err.count("\n") == 2 and "Traceback" not in err


def test_noise_command_without_gains_reports_counts(tmp_path, capsys):
    path, _, _ = _recording(tmp_path, 2e-12, seconds=2.0)
    assert main(["noise", str(path), "--json", "--duration", "1"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["readout_noise_a"] == {} and len(doc["without_gain"]) == 8
    assert all(c["sigma_counts_i"] > 0 for c in doc["channels"].values())

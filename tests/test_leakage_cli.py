"""`mntes-stream leakage REC` on simulated recordings, and `convert --kind` on MCAP (the linear baseline)."""

from __future__ import annotations

import json

import pytest

from mntes_stream.cli import main
from mntes_stream.core.validation import REQUIREMENT_PER_PW, expected_linear_nonlinearity_per_w
from mntes_stream.io.paramfile import load_params

pytestmark = pytest.mark.slow  # simulate + two offline conversions per recording


def _simulate(out, seconds, *sets, channels=6):
    argv = ["simulate", "--out", str(out), "--duration", str(seconds), "--channels", str(channels), "-q", "--json"]
    for s in sets:
        argv += ["--set", f"simulator.{s}"]
    assert main(argv) == 0


@pytest.fixture(scope="module")
def hwp_on(tmp_path_factory):
    """25 s, 6 channels (one saturated, one latched), HWP 2f = 10 fW; readout and housekeeping noise off,
    so MNTES's residual is measurable below the requirement in one detector's 25 s."""
    d = tmp_path_factory.mktemp("leak")
    _simulate(d / "run.mcap", 25, "nei_a_rthz=0.0", "hk_t_bath_noise_k=0.0", "hk_b_field_noise_t=0.0")
    return d


def test_linear_within_20_percent_of_the_true_nonlinearity_and_mntes_below_the_requirement(hwp_on, capsys):
    png = hwp_on / "leak.png"
    argv = ["leakage", str(hwp_on / "run.mcap"), "--truth", str(hwp_on / "run.truth.npz"),
            "--params", str(hwp_on / "run.params.toml"), "--png", str(png), "--json"]
    capsys.readouterr()
    assert main(argv) == 0
    res = json.loads(capsys.readouterr().out)
    truth = load_params(hwp_on / "run.params.toml")
    by_status = {}
    for r in res["detectors"]:
        by_status.setdefault(r["status"], []).append(r["detector"])
    assert len(by_status["ok"]) == 4 and len(by_status["no_linear_baseline"]) == 1, by_status  # + the saturated one
    assert res["f_hwp_source"] == "estimated" and res["f_hwp_hz"] == pytest.approx(0.77, abs=2e-4)
    for r in res["detectors"]:
        if r["status"] != "ok":
            assert r.get("linear_nl_per_pw") is None and r.get("mntes_nl_per_pw") is None
            continue
        expected = expected_linear_nonlinearity_per_w(truth[r["detector"]]) * 1e-12  # the model's I''/S
        assert r["linear_nl_signed_per_pw"] == pytest.approx(expected, rel=0.2)
        assert r["linear_nl_per_pw"] == pytest.approx(abs(expected), rel=0.2)
        assert r["linear_nl_sigma_per_pw"] < 0.02
        # MNTES against the truth: resolved below, or unresolved with a 3-sigma limit below, the requirement.
        assert (r["mntes_nl_per_pw"] or r["mntes_nl_bound_per_pw"]) < REQUIREMENT_PER_PW
    assert 0.5 < res["median_linear_nl_per_pw"] < 1.0
    assert res["median_mntes_nl_per_pw"] is None or res["median_mntes_nl_per_pw"] < REQUIREMENT_PER_PW
    assert res["median_mntes_nl_bound_per_pw"] < REQUIREMENT_PER_PW
    import matplotlib.image

    assert matplotlib.image.imread(png).shape[0] > 200
    # The figure is not replaced without --overwrite (before any conversion); --f-hwp must be positive.
    assert main(argv) == 2 and "--overwrite replaces it" in capsys.readouterr().err
    with pytest.raises(SystemExit) as refused:  # refused as the command line is read, in one line
        main(argv[:2] + ["--f-hwp", "0"])
    assert refused.value.code == 2 and "argument --f-hwp: expected a number (Hz) > 0, got '0'" in capsys.readouterr().err
    # The text form says the same in words.
    assert main(argv[:-1] + ["--overwrite", "-q"]) == 0
    text = capsys.readouterr().out
    assert "linear conversion (against MNTES, same counts): median 0." in text and "below the requirement" in text


def test_without_the_truth_mntes_is_not_claimed(hwp_on, capsys):
    assert main(["leakage", str(hwp_on / "run.mcap"), "--params", str(hwp_on / "run.params.toml"), "-q"]) == 0
    text = capsys.readouterr().out
    assert "no truth given" in text and "not measured" in text


def test_with_the_hwp_off_it_says_there_is_no_2f_line(tmp_path, capsys):
    _simulate(tmp_path / "off.mcap", 20, "hwp_2f_w=0.0", channels=3)
    capsys.readouterr()
    base = ["leakage", str(tmp_path / "off.mcap"), "--params", str(tmp_path / "off.params.toml"),
            "--truth", str(tmp_path / "off.truth.npz")]
    for extra in ([], ["--f-hwp", "0.77"]):
        assert main(base + extra + ["--json"]) == 0
        res = json.loads(capsys.readouterr().out)
        assert res["detectors_measured"] == 0 and res["median_linear_nl_per_pw"] is None
        assert res["median_mntes_nl_per_pw"] is None and res["median_mntes_nl_bound_per_pw"] is None
        assert res["message"].startswith("no 2f line to measure")
        assert all(r.get("linear_nl_per_pw") is None for r in res["detectors"])
    assert main(base + ["-q"]) == 0
    assert capsys.readouterr().out.startswith("no 2f line to measure (no HWP comb in the power spectrum)")


def test_convert_takes_kind_on_mcap_from_the_flag_or_the_config(tmp_path, capsys, caplog):
    _simulate(tmp_path / "r.mcap", 2, channels=4)  # one of them latched: no linear baseline
    capsys.readouterr()
    params = str(tmp_path / "r.params.toml")
    assert main(["convert", str(tmp_path / "r.mcap"), str(tmp_path / "lin.mcap"), "--params", params,
                 "--kind", "linear", "-q", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["converter_kind"] == "linear"
    conf = tmp_path / "converter.toml"
    conf.write_text(f'[converter]\nkind = "exact"\nparams = "{params}"\n')
    assert main(["convert", str(tmp_path / "r.mcap"), str(tmp_path / "ex.mcap"), "--params", params,
                 "--config", str(conf), "-q", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["converter_kind"] == "exact"
    assert main(["convert", str(tmp_path / "r.mcap"), str(tmp_path / "tb.mcap"), "--params", params,
                 "-q", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["converter_kind"] == "table"  # a simulate recording: the default
    from mntes_stream.feeds.recorded import RecordedPower

    lin = RecordedPower(tmp_path / "lin.mcap").read()
    ex = RecordedPower(tmp_path / "ex.mcap").read()
    (name,) = lin
    assert lin[name].detectors == ex[name].detectors
    import numpy as np

    from mntes_stream.core.flags import UNKNOWN_CHANNEL

    # The latched detector is left out of the linear baseline, said once, its power NaN + UNKNOWN_CHANNEL.
    left = [d for k, d in enumerate(lin[name].detectors) if np.all(lin[name].flags[k] & UNKNOWN_CHANNEL)]
    assert left == ["b0m0c003"] and np.all(np.isnan(lin[name].p_opt_w[3]))
    assert any("linear baseline: 1 detector(s)" in r.getMessage() and "b0m0c003" in r.getMessage()
               for r in caplog.records)
    both = np.isfinite(lin[name].p_opt_w) & np.isfinite(ex[name].p_opt_w)
    assert both[:2].all()  # c002 is saturated: flagged, NaN in both
    assert abs(lin[name].p_opt_w - ex[name].p_opt_w)[both].max() > 1e-17  # another conversion of the same counts


def test_a_file_that_is_not_a_truth_is_one_line(hwp_on, tmp_path, capsys):
    import numpy as np

    np.save(tmp_path / "one.npy", np.zeros(3))
    for bad in (hwp_on / "run.params.toml", tmp_path / "one.npy"):
        assert main(["leakage", str(hwp_on / "run.mcap"), "--truth", str(bad), "-q"]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "not a simulator truth file" in err[0], err

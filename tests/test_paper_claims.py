"""The paper's qualitative claims about Figure 1, and the figures themselves."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from mntes_stream.core.model import solve_operating_point, tune_bias_v
from mntes_stream.core.params import table1_params
from mntes_stream.core.scan import (
    retuned_d2i_dp2,
    retuned_response,
    scan_parameter,
    transition_width_peak_k,
    transition_width_peaks_k,
)


@pytest.fixture(scope="module")
def p():
    return table1_params()


def test_more_loading_lower_bias_higher_responsivity_steeply_higher_nonlinearity(p):
    res = scan_parameter(p, "p_opt_w", np.linspace(0.1e-12, 0.9e-12, 9))
    assert np.all(np.diff(res.v_thev_v) < 0)
    assert np.all(np.diff(res.abs_responsivity_a_per_w) > 0)
    nl = res.nonlinearity_per_pw
    assert np.all(np.diff(nl) > 0)
    # "Steep": convex growth, faster than the responsivity's.
    assert np.all(np.diff(nl, 2) > 0)
    assert nl[-1] / nl[0] > 2 * res.abs_responsivity_a_per_w[-1] / res.abs_responsivity_a_per_w[0]


@pytest.mark.parametrize("name", ["z_thev_re_ohm", "z_thev_im_ohm"])
def test_ten_percent_responsivity_boost_nearly_doubles_nonlinearity(p, name):
    from scipy.optimize import brentq

    s0, nl0, _ = retuned_response(p.replace(z_thev_ohm=0j))

    def boost(x):
        z = complex(x, 0) if name == "z_thev_re_ohm" else complex(0, x)
        return retuned_response(p.replace(z_thev_ohm=z))

    x10 = brentq(lambda x: boost(x)[0] / s0 - 1.10, 1e-4, 0.3)
    ratio = boost(x10)[1] / nl0
    # Paper: "nearly doubles". This model: 2.10x (resistive), 2.63x (inductive).
    assert 1.6 < ratio < 2.8, ratio


def test_transition_width_has_an_interior_nonlinearity_peak(p):
    peak = transition_width_peak_k(p)
    # Relative measure |d2I/dP2|/|S|: its peak sits near 11 mK.
    assert 10e-3 < peak < 12e-3
    nl = lambda iqr: retuned_response(p.replace(iqr_k=iqr))[1]  # noqa: E731
    assert nl(peak) > nl(peak / 3) and nl(peak) > nl(peak * 3)


def test_absolute_nonlinearity_peaks_at_the_papers_5_mk(p):
    """The paper's "greatest if the transition width is ~5 mK" holds for |d2I/dP2| in A/W^2 at fixed R_frac."""
    peaks = transition_width_peaks_k(p)
    assert 4.5e-3 < peaks["absolute"] < 6e-3 and 10e-3 < peaks["relative"] < 12e-3
    d2 = lambda iqr: retuned_d2i_dp2(p.replace(iqr_k=iqr))  # noqa: E731
    a = peaks["absolute"]
    assert d2(a) > d2(a * 0.9) and d2(a) > d2(a * 1.1)
    # Independent: the absolute peak from a finite-difference d2I/dP2 of the forward solve at fixed R_frac.
    def fd(iqr):
        q = p.replace(iqr_k=iqr)
        q = q.replace(v_thev_v=float(tune_bias_v(q, 0.7)))
        h = 2e-15
        i = [complex(solve_operating_point(q, q.p_opt_w + k * h).i_a) for k in (-1, 0, 1)]
        return abs(i[0] - 2 * i[1] + i[2]) / h**2
    assert fd(a) > fd(a * 0.7) and fd(a) > fd(a * 1.4)
    assert fd(a) == pytest.approx(d2(a), rel=1e-3)


def test_cli_model_json_and_figures(tmp_path):
    fig1, fig2 = tmp_path / "fig1.png", tmp_path / "fig2.png"
    out = subprocess.run(
        [sys.executable, "-m", "mntes_stream", "model", "--json", "--figure", str(fig1), "--response-figure", str(fig2)],
        capture_output=True, text=True, check=True,
    )
    d = json.loads(out.stdout)
    for key in ("abs_responsivity_a_per_w", "loop_gain", "alpha", "beta", "r_frac", "t_tes_k", "v_thev_v",
                "i_peak_a", "g_bar_w_per_k", "tau0_s", "d2i_dp2_a_per_w2", "nonlinearity_per_pw"):
        assert isinstance(d[key], float), key
    assert d["v_thev_v"] == pytest.approx(0.8e-6)
    for f in (fig1, fig2):
        assert f.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and f.stat().st_size > 20_000


def test_cli_model_tune_and_params_file(tmp_path):
    from mntes_stream.io.paramfile import dump_params

    path = tmp_path / "p.toml"
    dump_params([table1_params("a"), table1_params("b", t_c_k=0.19)], path)
    out = subprocess.run(
        [sys.executable, "-m", "mntes_stream", "model", "--params", str(path), "--detector", "b",
         "--tune-r-frac", "0.6", "--json"],
        capture_output=True, text=True, check=True,
    )
    d = json.loads(out.stdout)
    assert d["detector_id"] == "b" and d["r_frac"] == pytest.approx(0.6, rel=1e-9)
    bad = subprocess.run(
        [sys.executable, "-m", "mntes_stream", "model", "--params", str(path), "--detector", "zz"],
        capture_output=True, text=True,
    )
    assert bad.returncode == 2 and "not in" in bad.stderr and "Traceback" not in bad.stderr

"""PNG figures (matplotlib, Agg backend). An edge module: it writes files."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mntes_stream.core.model import invert_current, readout_current_a, solve_operating_point, tune_bias_v
from mntes_stream.core.params import DetectorParams
from mntes_stream.core.scan import SCANS, retuned_response, scan_parameter, transition_width_peaks_k

__all__ = ["figure_parameter_dependence", "figure_response_function", "pyplot"]


def pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def figure_parameter_dependence(p: DetectorParams, path: str | Path, r_frac: float = 0.7) -> dict:
    """Paper Figure 1: |S| and nonlinearity against loading, width, Re z, Im z.

    Returns the scan results as plain lists (for JSON and tests).
    """
    plt = pyplot()
    fig, axes = plt.subplots(2, len(SCANS), figsize=(4.2 * len(SCANS), 7), sharey="row")
    s0, nl0, _ = retuned_response(p, r_frac)
    scale = {"p_opt_w": 1e12, "iqr_k": 1e3}
    out = {}
    for col, name in enumerate(SCANS):
        res = scan_parameter(p, name, r_frac=r_frac)
        x = res.values * scale.get(name, 1.0)
        xf = res.fiducial * scale.get(name, 1.0)
        axes[0, col].plot(x, res.abs_responsivity_a_per_w / 1e6, color="C0")
        axes[0, col].plot([xf], [s0 / 1e6], "*", ms=14, color="C3", label="fiducial (Table 1)")
        axes[1, col].plot(x, res.nonlinearity_per_pw, color="C1")
        axes[1, col].plot([xf], [nl0], "*", ms=14, color="C3")
        axes[1, col].axhline(0.014, ls=":", color="k", lw=1, label="requirement 0.014 / pW")
        axes[1, col].set_xlabel(res.label)
        if name == "iqr_k":
            for ax in axes[:, col]:
                ax.set_xscale("log")
            # Both measures: the relative one peaks near 11 mK, the absolute |d2I/dP2| (the
            # paper's Figure 1 quantity) near the paper's 5 mK.
            peaks = transition_width_peaks_k(p, r_frac)
            twin = axes[1, col].twinx()
            twin.plot(x, res.abs_d2i_dp2_a_per_w2 / 1e18, color="C2", ls="--", label="|d2I/dP2| [10^18 A/W^2]")
            for measure, color in (("relative", "C1"), ("absolute", "C2")):
                axes[1, col].axvline(peaks[measure] * 1e3, color=color, lw=0.8, ls=":")
            twin.legend(loc="lower center", fontsize=8)
            out["iqr_peaks_k"] = peaks
        out[name] = {
            "values": res.values.tolist(),
            "abs_responsivity_a_per_w": res.abs_responsivity_a_per_w.tolist(),
            "nonlinearity_per_pw": res.nonlinearity_per_pw.tolist(),
            "abs_d2i_dp2_a_per_w2": res.abs_d2i_dp2_a_per_w2.tolist(),
        }
    axes[0, 0].set_ylabel("|S| [10^6 A/W]")
    axes[1, 0].set_ylabel("|d2I/dP2| / |S| [1/pW]")
    axes[1, 0].set_yscale("log")
    axes[0, 0].legend(loc="best", fontsize=8)
    axes[1, 0].legend(loc="best", fontsize=8)
    fig.suptitle(f"Responsivity and leading-order nonlinearity, bias re-tuned to R_frac = {r_frac}")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return out


def figure_response_function(p: DetectorParams, path: str | Path, r_frac: float | None = None) -> None:
    """Paper Figure 2: response I(P) and its inverse P(I) for one detector."""
    plt = pyplot()
    v = p.v_thev_v if r_frac is None else float(tune_bias_v(p, r_frac))
    p_grid = np.linspace(0.0, 1.4 * p.p_sat_w, 600)
    op = solve_operating_point(p, p_grid, v_thev_v=v)
    i_meas = readout_current_a(p, op.i_a)
    inv = invert_current(p, i_meas, v_thev_v=v)
    ok = op.state == 0
    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4.5))
    a.plot(p_grid * 1e12, np.abs(i_meas) * 1e6, color="C0")
    a.set_xlabel("optical power P_opt [pW]")
    a.set_ylabel("|I| (peak) [uA]")
    a.set_title("MNTES response function")
    a.axvline(p.p_opt_w * 1e12, ls=":", color="k", lw=1)
    b.plot(np.abs(i_meas[ok]) * 1e6, inv.p_opt_w[ok] * 1e12, color="C1")
    b.set_xlabel("|I| (peak) [uA]")
    b.set_ylabel("reconstructed P_opt [pW]")
    b.set_title("inverse: counts -> optical power")
    fig.suptitle(f"{p.detector_id}: V_Thev = {v * 1e6:.3f} uV RMS, T_bath = {p.t_bath_k * 1e3:.0f} mK")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)

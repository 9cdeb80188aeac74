"""The validation study's report: Markdown with tables and PNG figures (an edge module: it writes files)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from mntes_stream.core.validation import REQUIREMENT_PER_PW, StudyResult
from mntes_stream.reports.plots import pyplot

__all__ = ["write_report", "headline_rows", "headline_markdown", "to_jsonable"]

_LABELS = {"linear": "linear (P0 + dI/S)", "electrical": "electrical (SPT-3G)",
           "table": "MNTES (tables)", "exact": "MNTES (exact)", "grid": "MNTES (grid)"}
_COLORS = {"linear": "C3", "electrical": "C1", "table": "C0", "exact": "C2", "grid": "C4"}


def to_jsonable(x):
    """Numpy scalars/arrays and non-finite floats to plain JSON values."""
    if isinstance(x, dict):
        return {str(k): to_jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [to_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return to_jsonable(x.tolist())
    if isinstance(x, (np.integer,)):
        return int(x)
    if isinstance(x, (float, np.floating)):
        x = float(x)
        return x if math.isfinite(x) else None
    return x


def _fmt(x, kind="g", digits=3) -> str:
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "n/a"
    if kind == "pct":
        return f"{100 * x:+.{digits}g} %"
    return f"{x:.{digits}g}"


# (label, key in per-converter results, format, unit)
_ROWS = [
    ("HWP 2f -> 4f: effective nonlinearity", "nonlinearity_per_pw", "g", "1/pW"),
    ("HWP 4f leak (2f amplitude A)", "leak_4f_w", "g", "W"),
    ("Jupiter: peak error", "jupiter_peak_frac_error", "pct", ""),
    ("Jupiter: FWHM error", "jupiter_fwhm_frac_error", "pct", ""),
    ("Jupiter: shape residual (rms / peak)", "jupiter_shape_rms_frac", "g", ""),
    ("CMB dipole: calibration gain bias", "dipole_gain_bias", "pct", ""),
    ("gain drift with bath temperature", "drift_gain_per_mk", "g", "1/mK"),
    ("offset drift with bath temperature", "drift_offset_w_per_mk", "g", "W/mK"),
    ("gain drift with magnetic field", "drift_gain_per_ut", "g", "1/uT"),
    ("offset drift with magnetic field", "drift_offset_w_per_ut", "g", "W/uT"),
]


def headline_rows(summary: dict) -> list[list[str]]:
    kinds = list(summary["converters"])
    rows = [["effect", "unit"] + [_LABELS.get(k, k) for k in kinds]]
    for label, key, kind, unit in _ROWS:
        rows.append([label, unit] + [_fmt(summary["converters"][k].get(key), kind) for k in kinds])
    return rows


def _markdown_table(rows: list[list[str]]) -> str:
    out = ["| " + " | ".join(rows[0]) + " |", "|" + "---|" * len(rows[0])]
    out += ["| " + " | ".join(r) + " |" for r in rows[1:]]
    return "\n".join(out)


def headline_markdown(summary: dict) -> str:
    """The headline table (Markdown), one column per converter."""
    return _markdown_table(headline_rows(summary))


def _robustness_markdown(rob: dict) -> str:
    rows = [["parameter", "assumed 1-sigma error", "residual nonlinearity at it [1/pW]", "abs. 2f gain error at it",
             "largest error meeting 0.014/pW", "margin (largest / assumed)"]]
    for r in rob["one_at_a_time"]:
        def err(x):
            return f"{100 * x:.3g} %" if r["mode"] == "frac" else f"{x:.3g} {r['unit']}".strip()

        largest = err(r["largest_error_meeting_requirement"])
        if r["bound"] == "above":
            largest = "> " + largest
        elif r["bound"] == "below":
            largest = "< " + largest
        rows.append([r["label"], err(r["realistic_error"]), _fmt(r["nonlinearity_at_realistic_per_pw"]),
                     f"{100 * r['gain_error_at_realistic']:.2g} %", largest, _fmt(r["margin"])])
    a = rob["all_together"]
    rows.append(["all together (random draws)", "as above", f"median {_fmt(a['median_per_pw'])}, "
                 f"95% {_fmt(a['p95_per_pw'])}", "", f"{_fmt(a['largest_scale_p95_meeting_requirement'])} x assumed "
                 "(95% of draws)", _fmt(a["largest_scale_p95_meeting_requirement"])])
    text = _markdown_table(rows)
    if a.get("by_source"):
        src = [["error source (largest first)", "share of the variance (linear)", "median without it [1/pW]",
                "median drop"]]
        src += [[e["label"], f"{100 * e['variance_share']:.2g} %", _fmt(e["median_without_per_pw"]),
                 f"{100 * e['median_drop_frac']:.2g} %"] for e in a["by_source"]]
        text += ("\n\nThe all-together median by error source (which measurement to improve first; linear "
                 f"prediction of the median {_fmt(a['linear_prediction_median_per_pw'])} /pW):\n\n"
                 + _markdown_table(src))
    return text


# --- figures ----------------------------------------------------------------------------------

def _harmonic_lines(ax, f_hwp, fmax):
    for h in range(1, 7):
        f = h * f_hwp
        if f < fmax:
            ax.axvline(f, color="0.6", lw=0.8, ls=":" if h not in (2, 4) else "--")
            ax.text(f, 1.0, f"{h}f", transform=ax.get_xaxis_transform(), ha="center", va="bottom", fontsize=8)


def _save(plt, fig, path, dpi: int = 100) -> None:
    fig.tight_layout()
    fig.savefig(path, dpi=dpi)
    plt.close(fig)


def _psd(x, fs):
    from scipy.signal import welch

    x = np.asarray(x) - np.mean(x)
    nper = min(len(x), 1 << 14)
    return welch(x, fs=fs, nperseg=nper)


def _robustness_curves(ax, r: dict, legend_size: int = 7) -> None:
    """One line per calibration parameter: residual nonlinearity against error / assumed error."""
    from mntes_stream.core.validation import CALIBRATION_ERRORS

    for i, (name, curve) in enumerate(r["curves"].items()):
        c = np.where(np.isfinite(curve), curve, np.nan)
        ax.loglog(r["multiples"], np.maximum(c, 1e-9), color=f"C{i % 10}", ls="-" if i < 10 else "--",
                  lw=1, label=CALIBRATION_ERRORS[name][0])
    ax.axhline(REQUIREMENT_PER_PW, color="k", ls=":", label="requirement 0.014 / pW")
    ax.axvline(1.0, color="0.5", lw=0.8)
    ax.set_xlabel("calibration error / assumed 1-sigma error")
    ax.set_ylabel("residual effective nonlinearity [1/pW]")
    ax.set_title("MNTES with one wrong calibration parameter")
    ax.legend(fontsize=legend_size, ncol=2)


def _residual_spectra(ax, s: dict) -> None:
    """ASD of P_rec - P_true for each converter, HWP harmonics marked."""
    for k, x in s["rec_w"].items():
        f, p = _psd(np.asarray(x) - s["truth_w"], s["fs_hz"])
        ax.loglog(f[1:], np.sqrt(p[1:]), color=_COLORS.get(k), lw=0.8, label=_LABELS.get(k, k))
    _harmonic_lines(ax, s["f_hwp_hz"], s["fs_hz"] / 2)
    ax.set_xlabel("frequency [Hz]")
    ax.set_ylabel("ASD of P_rec - P [W/sqrt(Hz)]")
    ax.legend(fontsize=7, loc="lower left")


def figure_timestreams(res: StudyResult, path: Path) -> None:
    plt = pyplot()
    fig, axes = plt.subplots(3, 1, figsize=(10, 10))
    j = res.figures["jupiter"]
    t = j["t_s"]
    axes[0].plot(t, j["truth_w"] * 1e12, color="k", lw=2, label="truth")
    for k, p in j["rec_w"].items():
        axes[0].plot(t, p * 1e12, color=_COLORS.get(k), lw=1, label=_LABELS.get(k, k))
    axes[0].set_ylabel("P - loading [pW]")
    axes[0].set_title("Jupiter crossing: reconstructed optical power")
    axes[0].legend(fontsize=8)
    for k, p in j["rec_w"].items():
        axes[1].plot(t, (p - j["truth_w"]) * 1e12, color=_COLORS.get(k), lw=1, label=_LABELS.get(k, k))
    axes[1].set_ylabel("P_rec - P [pW]")
    axes[1].set_title("Jupiter crossing: residual")
    axes[1].set_yscale("symlog", linthresh=1e-6)
    h = res.figures["hwp"]
    for k, r in h["residual_w"].items():
        axes[2].plot(h["t_s"], r * 1e15, color=_COLORS.get(k), lw=1, label=_LABELS.get(k, k))
    axes[2].set_ylabel("P_rec - P [fW]")
    axes[2].set_xlabel("time [s]")
    axes[2].set_title("HWP 2f signal: residual (linear conversion leaks 4f and a DC offset)")
    axes[2].legend(fontsize=8)
    _save(plt, fig, path)


def figure_spectra(res: StudyResult, path: Path) -> None:
    plt = pyplot()
    s = res.figures["spectra"]
    fs, fh = s["fs_hz"], s["f_hwp_hz"]
    fig, (a, b) = plt.subplots(2, 1, figsize=(10, 8), sharex=True)
    f, p = _psd(s["truth_w"], fs)
    a.loglog(f[1:], np.sqrt(p[1:]), color="k", lw=1.5, label="truth")
    for k, x in s["rec_w"].items():
        f, p = _psd(x, fs)
        a.loglog(f[1:], np.sqrt(p[1:]), color=_COLORS.get(k), lw=0.8, label=_LABELS.get(k, k))
    _harmonic_lines(a, fh, fs / 2)
    a.set_ylabel("ASD of P_rec [W/sqrt(Hz)]")
    a.legend(fontsize=8, loc="lower left")
    _residual_spectra(b, s)
    a.set_title("Reconstructed power (photon + 1/f + readout noise); HWP harmonics marked", pad=14)
    b.set_title("Residual P_rec - P_true (4f: the nonlinearity's up-conversion)", pad=14)
    _save(plt, fig, path)


def _relative_gain(wg: dict, nominal: float) -> np.ndarray:
    """Gain relative to its value at the tuning point (interpolated): the drift, not the offset."""
    g0 = float(np.interp(nominal, wg["env"], wg["gain"]))
    return wg["gain"] / g0 - 1


def figure_drift(res: StudyResult, path: Path) -> None:
    plt = pyplot()
    d = res.figures["drift"]
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    for ax, name, scale, xlabel, nominal in ((axes[0], "t_bath", 1e3, "bath temperature [mK]", 0.1),
                                             (axes[1], "b_field", 1e6, "magnetic field [uT]", 0.0)):
        for k, wg in d[name].items():
            ax.plot(wg["env"] * scale, _relative_gain(wg, nominal) * 100, "o-", ms=3, color=_COLORS.get(k),
                    label=_LABELS.get(k, k))
        ax.set_xlabel(xlabel)
        ax.set_ylabel("gain change from the tuning point [%]")
    axes[0].legend(fontsize=8)
    fig.suptitle("Gain drift (2f probe) while the environment drifts; bias tuned at 100 mK, 0 uT")
    _save(plt, fig, path)


def figure_robustness(res: StudyResult, path: Path) -> None:
    plt = pyplot()
    r = res.figures["robustness"]
    fig, (a, b) = plt.subplots(1, 2, figsize=(12, 4.8), gridspec_kw={"width_ratios": [2, 1]})
    _robustness_curves(a, r)
    x = np.asarray(r["all_together"])
    x = x[np.isfinite(x)]
    b.hist(np.log10(np.maximum(x, 1e-9)), bins=20, color="C0")
    b.axvline(math.log10(REQUIREMENT_PER_PW), color="k", ls=":")
    b.set_xlabel("log10 residual nonlinearity [1/pW]")
    b.set_title("all errors at once (assumed levels)")
    _save(plt, fig, path)


def figure_jupiter_sweep(res: StudyResult, path: Path) -> None:
    plt = pyplot()
    s = res.figures["jupiter_sweep"]
    fig, ax = plt.subplots(figsize=(6, 4.2))
    peaks = np.asarray(s["peak_w"]) * 1e12
    for k, e in s["peak_frac_error"].items():
        ax.semilogy(peaks, np.maximum(np.abs(e), 1e-9), "o-", color=_COLORS.get(k), label=_LABELS.get(k, k))
    ax.set_xlabel("source peak [pW]")
    ax.set_ylabel("|peak error| (fraction)")
    ax.set_title("Compact-source peak error")
    ax.legend(fontsize=8)
    _save(plt, fig, path)


def figure_overview(res: StudyResult, path: Path) -> None:
    """Four panels for the README: 4f spectrum, Jupiter residual, bath drift, robustness."""
    plt = pyplot()
    fig, ax = plt.subplots(2, 2, figsize=(12, 8.5))
    s = res.figures["spectra"]
    _residual_spectra(ax[0, 0], s)
    ax[0, 0].set_xlim(0.05, s["fs_hz"] / 2)
    ax[0, 0].set_title("residual spectrum with a 2f HWP signal", pad=14)
    j = res.figures["jupiter"]
    for k, p in j["rec_w"].items():
        ax[0, 1].plot(j["t_s"], p * 1e12, color=_COLORS.get(k), lw=1, label=_LABELS.get(k, k))
    ax[0, 1].plot(j["t_s"], j["truth_w"] * 1e12, "k--", lw=1, label="truth")
    ax[0, 1].set_title("Jupiter crossing (loading subtracted)")
    ax[0, 1].set_xlabel("time [s]")
    ax[0, 1].set_ylabel("P [pW]")
    ax[0, 1].legend(fontsize=7)
    for k, wg in res.figures["drift"]["t_bath"].items():
        ax[1, 0].plot(wg["env"] * 1e3, _relative_gain(wg, 0.1) * 100, "o-", ms=3, color=_COLORS.get(k),
                      label=_LABELS.get(k, k))
    ax[1, 0].set_title("gain drift with bath temperature")
    ax[1, 0].set_xlabel("bath temperature [mK]")
    ax[1, 0].set_ylabel("gain change from 100 mK [%]")
    ax[1, 0].legend(fontsize=7)
    _robustness_curves(ax[1, 1], res.figures["robustness"], legend_size=6)
    _save(plt, fig, path, dpi=90)


FIGURES = {
    "timestreams.png": figure_timestreams,
    "spectra.png": figure_spectra,
    "drift.png": figure_drift,
    "robustness.png": figure_robustness,
    "jupiter_sweep.png": figure_jupiter_sweep,
    "overview.png": figure_overview,
}


def write_report(res: StudyResult, out_dir: str | Path) -> dict:
    """Write ``report.md``, ``summary.json`` and the PNG figures into ``out_dir``.

    Returns
    -------
    dict
        ``{"report": path, "summary": path, "figures": {name: path}}`` (strings).
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    figures = {}
    for name, fn in FIGURES.items():
        fn(res, out / name)
        figures[name] = str(out / name)
    s = res.summary
    a = s["assumptions"]
    lines = [
        "# MNTES validation study",
        "",
        f"Simulated {a['detector']}; converters see the true environment at every sample. "
        f"Requirement: effective nonlinearity < {REQUIREMENT_PER_PW} / pW. "
        f"{'Quick run (--quick). ' if a['quick'] else ''}Elapsed {s['elapsed_s']:.1f} s.",
        "",
        "## Effects of paper section 2",
        "",
        headline_markdown(s),
        "",
        f"Effective nonlinearity: eps = 4 a4 / (f' A^2) from a pure 2f HWP signal of amplitude "
        f"A = {a['hwp_2f_w'] * 1e15:.3g} fW on the loading (noise-free, quantised counts); the linear "
        f"conversion's expected leading-order value Re(I''/S) is {s['expected_linear_nonlinearity_per_pw']:.4g} / pW. "
        f"Jupiter: Gaussian crossing, peak {a['jupiter_peak_w'] * 1e12:.3g} pW, FWHM {a['jupiter_fwhm_s']} s. "
        f"Dipole: {a['dipole']['amplitude_k_cmb'] * 1e3:.3g} mK_CMB = {a['dipole']['amplitude_w']:.3g} W "
        f"({a['dipole']['band_center_hz'] / 1e9:.0f} GHz, {a['dipole']['fractional_bandwidth']:.0%} band, "
        f"efficiency {a['dipole']['optical_efficiency']}), sky loading "
        f"{a['dipole']['sky_loading_offset_frac']:+.0%} off the calibration point, with a "
        f"{a['dipole']['hwp_2f_w'] * 1e15:.3g} fW 2f signal. Drifts: bath "
        f"{a['drift']['t_bath_k'][0] * 1e3:.0f}-{a['drift']['t_bath_k'][1] * 1e3:.0f} mK, field "
        f"{a['drift']['b_field_t'][0] * 1e6:.0f} to {a['drift']['b_field_t'][1] * 1e6:.0f} uT.",
        "",
        "## Robustness to calibration errors (MNTES, exact inverse, one parameter wrong at a time)",
        "",
        _robustness_markdown(s["robustness"]),
        "",
        f"Run with a static field of {s['robustness']['b_field_t'] * 1e6:.0f} uT so the magnetic coefficients matter. "
        "The bias error is applied to the housekeeping bias reading the converter uses.",
        "",
        "## Figures",
        "",
    ]
    for name in FIGURES:
        lines += [f"![{name}]({name})", ""]
    (out / "report.md").write_text("\n".join(lines))
    (out / "summary.json").write_text(json.dumps(to_jsonable(s), indent=2))
    return {"report": str(out / "report.md"), "summary": str(out / "summary.json"), "figures": figures}

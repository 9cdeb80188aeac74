"""Ground-calibration report: fit-quality PNGs per measurement and a Markdown summary (edge module)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mntes_stream.core.calib.campaign import pulls
from mntes_stream.core.calib.endtoend import REQUIREMENT_PER_PW, calibration_nonlinearity
from mntes_stream.core.calib.fit import DetectorFit
from mntes_stream.core.calib.forward import PARAM_NAMES, PARAM_UNITS, Design, predict_counts
from mntes_stream.core.calib.measurements import KINDS, SWEPT_AXIS, Campaign
from mntes_stream.reports.plots import pyplot

__all__ = ["Evaluation", "evaluate", "write_report", "HWP_AMPLITUDE_W"]

HWP_AMPLITUDE_W = 0.1e-12
# Swept-axis display: (label, scale); network analyses are shown relative to the bias frequency.
_AXIS = {
    "p_opt_w": ("P_opt [pW]", 1e12),
    "b_field_t": ("B [uT]", 1e6),
    "bias_ratio": ("V / V0", 1.0),
    "t_bath_k": ("T_bath [mK]", 1e3),
    "freq_hz": ("f - f_bias [kHz]", 1e-3),
}


@dataclass
class Evaluation:
    """What the report shows besides the fits: truth comparison and end-to-end nonlinearity."""

    summary: dict = field(default_factory=dict)
    pull_ids: list = field(default_factory=list)
    pulls: np.ndarray | None = None
    eps_arctan: dict = field(default_factory=dict)   # detector id -> eps_eff (1/pW)
    eps_tabulated: dict = field(default_factory=dict)
    eps_linear: dict = field(default_factory=dict)
    converter: str = ""


def _eps(truth_p, fitted, kind) -> dict:
    res = calibration_nonlinearity(truth_p, fitted, kind=kind, amplitude_w=HWP_AMPLITUDE_W)
    return {d: r.eps_per_w * 1e-12 for d, r in res.items()}


def evaluate(campaign: Campaign, fits: dict[str, DetectorFit], arctan: dict, tabulated: dict,
             truth: dict | None, converter_kind: str = "table") -> Evaluation:
    """Summary numbers; with ``truth`` also pulls and the end-to-end effective nonlinearity."""
    ok = [d for d, f in fits.items() if f.ok]
    ev = Evaluation(converter=converter_kind)
    s = ev.summary
    chi = [f.chi2 / f.ndf for f in fits.values() if f.ok]
    s["chi2_per_ndf_median"] = float(np.median(chi)) if chi else math.nan
    if ok:
        rel = np.array([fits[d].sigma for d in ok])
        s["sigma_median"] = {n: float(v) for n, v in zip(PARAM_NAMES, np.median(rel, axis=0))}
    if truth is None or not ok:
        return ev
    ev.pull_ids, ev.pulls = pulls(fits, truth)
    within = np.abs(ev.pulls) < 3
    s["pull_mean"] = {n: float(v) for n, v in zip(PARAM_NAMES, ev.pulls.mean(axis=0))}
    s["pull_std"] = {n: float(v) for n, v in zip(PARAM_NAMES, ev.pulls.std(axis=0, ddof=1) if len(ok) > 1 else [math.nan] * len(PARAM_NAMES))}
    s["within_3sigma_fraction"] = {n: float(v) for n, v in zip(PARAM_NAMES, within.mean(axis=0))}
    s["all_within_3sigma_fraction"] = float(np.all(within, axis=1).mean())
    truth_p = {d: truth[d][0] for d in ok}
    ev.eps_arctan = _eps(truth_p, {d: arctan[d] for d in ok}, converter_kind)
    tab_ok = [d for d in ok if d in tabulated]
    if tab_ok:
        ev.eps_tabulated = _eps({d: truth_p[d] for d in tab_ok}, {d: tabulated[d] for d in tab_ok}, converter_kind)
    ev.eps_linear = _eps(truth_p, {d: arctan[d] for d in ok}, "linear")
    a = np.abs(list(ev.eps_arctan.values()))
    s.update({
        "converter": converter_kind,
        "hwp_amplitude_pw": HWP_AMPLITUDE_W * 1e12,
        "requirement_per_pw": REQUIREMENT_PER_PW,
        "eps_eff_max_per_pw": float(a.max()),
        "eps_eff_median_per_pw": float(np.median(a)),
        "eps_eff_below_requirement_fraction": float(np.mean(a < REQUIREMENT_PER_PW)),
        "margin_factor": float(REQUIREMENT_PER_PW / a.max()) if a.max() > 0 else math.inf,
        "eps_eff_linear_median_per_pw": float(np.median(np.abs(list(ev.eps_linear.values())))),
    })
    if ev.eps_tabulated:
        t = np.abs(list(ev.eps_tabulated.values()))
        s["eps_eff_tabulated_max_per_pw"] = float(t.max())
        s["eps_eff_tabulated_median_per_pw"] = float(np.median(t))
        s["margin_factor_tabulated"] = float(REQUIREMENT_PER_PW / t.max()) if t.max() > 0 else math.inf
    else:
        s["eps_eff_tabulated_max_per_pw"] = math.nan
    return ev


# --------------------------------------------------------------------------- figures


def _model_and_residuals(campaign: Campaign, fits: dict[str, DetectorFit]):
    """Per usable detector: its sweeps with model counts and normalised residuals."""
    out = {}
    for d, f in fits.items():
        if f.theta is None or not f.used_sweeps:
            continue
        det = campaign.detectors[d]
        design = Design.from_detector(det, f.used_sweeps)
        model = predict_counts(f.theta, design)
        rows, start = [], 0
        for s in f.used_sweeps:
            sl = slice(start, start + len(s))
            start += len(s)
            rows.append((s, model[sl], (s.counts - model[sl]) / s.sigma_counts))
        out[d] = (det, rows)
    return out


def _x(s, det):
    label, scale = _AXIS[s.axis]
    x = s.swept - (det.bias_freq_hz if s.axis == "freq_hz" else 0.0)
    return x * scale, label


def _figure_kind(path: Path, kind: str, per_det: dict, fits: dict, n_examples: int = 3) -> None:
    plt = pyplot()
    fig, (a, b, c) = plt.subplots(1, 3, figsize=(15, 4.3))
    examples = [d for d in per_det if fits[d].ok][:n_examples]
    for k, d in enumerate(examples):
        det, rows = per_det[d]
        for s, model, _ in rows:
            if s.kind != kind:
                continue
            x, label = _x(s, det)
            g = det.gain_abs_a_per_count
            order = np.argsort(x)
            a.plot(x, np.abs(s.counts) * g * 1e6, "o", ms=3, color=f"C{k}")
            a.plot(x[order], np.abs(model[order]) * g * 1e6, "-", lw=1, color=f"C{k}")
            a.set_xlabel(label)
        a.plot([], [], "o-", color=f"C{k}", label=d)
    a.set_ylabel("|I| (peak) [uA]")
    a.set_title("data (points) and fitted model (lines)")
    if examples:
        a.legend(fontsize=7)
    chi = []
    for det, rows in per_det.values():
        for s, _, res in rows:
            if s.kind != kind:
                continue
            x, label = _x(s, det)
            b.plot(x, res.real, ".", ms=1.5, color="C0", alpha=0.4)
            b.plot(x, res.imag, ".", ms=1.5, color="C1", alpha=0.4)
            b.set_xlabel(label)
            chi.append(float(np.mean(np.abs(res) ** 2) / 2))
    b.plot([], [], ".", color="C0", label="Re")
    b.plot([], [], ".", color="C1", label="Im")
    b.axhline(3, ls=":", color="k", lw=0.8)
    b.axhline(-3, ls=":", color="k", lw=0.8)
    b.set_ylabel("(data - model) / sigma")
    b.set_title(f"normalised residuals, {len(per_det)} detectors")
    b.legend(fontsize=7, loc="upper right")
    if chi:
        c.hist(chi, bins=30, color="C2")
    c.axvline(1.0, ls="--", color="k", lw=1, label="expected 1")
    c.set_xlabel("chi2 / (2 n_points) per sweep")
    c.set_ylabel("sweeps")
    c.set_title("fit quality per sweep")
    c.legend(fontsize=7)
    fig.suptitle(f"{kind} ({SWEPT_AXIS[kind]} swept)")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _figure_pulls(path: Path, ev: Evaluation) -> None:
    plt = pyplot()
    n = len(PARAM_NAMES)
    cols = 5
    fig, axes = plt.subplots(math.ceil(n / cols), cols, figsize=(3.2 * cols, 2.6 * math.ceil(n / cols)))
    xs = np.linspace(-4, 4, 200)
    for k, ax in enumerate(axes.flat):
        if k >= n:
            ax.axis("off")
            continue
        p = np.clip(ev.pulls[:, k], -5, 5)
        ax.hist(p, bins=np.linspace(-5, 5, 26), density=True, color="C0", alpha=0.7)
        ax.plot(xs, np.exp(-xs**2 / 2) / np.sqrt(2 * np.pi), "k-", lw=1)
        ax.set_title(f"{PARAM_NAMES[k]}\nmean {ev.pulls[:, k].mean():+.2f} std {ev.pulls[:, k].std(ddof=1):.2f}", fontsize=8)
    fig.suptitle(f"pulls (fit - truth) / sigma, {len(ev.pull_ids)} detectors; curve: unit normal")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _figure_nonlinearity(path: Path, ev: Evaluation) -> None:
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(8, 4.5))
    series = [("MNTES, fitted arctan", ev.eps_arctan, "C0"), ("MNTES, tabulated R(T)", ev.eps_tabulated, "C1"),
              ("linear conversion (fitted parameters)", ev.eps_linear, "C3")]
    vals = [np.abs(list(v.values())) for _, v, _ in series if v]
    lo = max(min(float(v.min()) for v in vals), 1e-9)
    bins = np.logspace(np.log10(lo) - 0.2, np.log10(max(float(v.max()) for v in vals)) + 0.2, 50)
    for label, v, color in series:
        if v:
            ax.hist(np.maximum(np.abs(list(v.values())), lo), bins=bins, alpha=0.6, color=color, label=label)
    ax.axvline(REQUIREMENT_PER_PW, color="k", ls="--", label="requirement 0.014 / pW")
    ax.set_xscale("log")
    ax.set_xlabel("|eps_eff| [1/pW]  (4 a4 / A^2, HWP 2f signal of A = %.2g pW)" % (HWP_AMPLITUDE_W * 1e12))
    ax.set_ylabel("detectors")
    ax.set_title(f"end to end: true detector -> counts -> {ev.converter} converter with fitted parameters")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


# --------------------------------------------------------------------------- summary


def _fmt(x: float) -> str:
    return f"{x:.3g}" if isinstance(x, (int, float)) and math.isfinite(x) else str(x)


def write_report(directory: str | Path, campaign: Campaign, fits: dict[str, DetectorFit], ev: Evaluation,
                 params_path: str | Path | None = None) -> Path:
    """PNG per measurement kind (+ pulls and nonlinearity with truth) and ``summary.md``; returns its path."""
    out = Path(directory)
    out.mkdir(parents=True, exist_ok=True)
    per_det = _model_and_residuals(campaign, fits)
    figures = {}
    for kind in KINDS:
        name = f"fit_{kind}.png"
        _figure_kind(out / name, kind, per_det, fits)
        figures[kind] = name
    if ev.pulls is not None:
        _figure_pulls(out / "pulls.png", ev)
    if ev.eps_arctan:
        _figure_nonlinearity(out / "nonlinearity.png", ev)
    s = ev.summary
    status = {k: [d for d, f in fits.items() if f.status == k] for k in ("ok", "flagged", "failed")}
    lines = ["# Ground calibration report", ""]
    lines += [f"Campaign: {len(campaign)} detectors; metadata `{campaign.metadata}`."]
    if params_path:
        lines += [f"Parameter file: `{params_path}` (only the `ok` detectors; every fit's record is in its `[metadata.calibration]`)."]
    lines += ["", "## Outcome", "",
              "| ok | flagged | failed |", "|---|---|---|",
              f"| {len(status['ok'])} | {len(status['flagged'])} | {len(status['failed'])} |", ""]
    bad = [(d, fits[d]) for d in status["flagged"] + status["failed"]]
    if bad:
        lines += ["| detector | status | reasons |", "|---|---|---|"]
        lines += [f"| {d} | {f.status} | {'; '.join(f.reasons)} |" for d, f in bad]
        lines += [""]
    lines += ["## Fit quality per measurement", "",
              "Residuals are weighted by the known noise; the covariance is `(J^T J)^-1` with no chi2 rescaling.",
              f"Median chi2/ndf over usable detectors: {s.get('chi2_per_ndf_median', math.nan):.3f}.", "",
              "| measurement | sweeps | median chi2 per point | figure |", "|---|---|---|---|"]
    for kind in KINDS:
        c = [float(np.mean(np.abs(res) ** 2) / 2) for _, rows in per_det.values() for sw, _, res in rows if sw.kind == kind]
        lines.append(f"| {kind} | {len(c)} | {_fmt(float(np.median(c)) if c else math.nan)} | ![{kind}]({figures[kind]}) |")
    if "sigma_median" in s:
        lines += ["", "## Uncertainties (median over usable detectors)", "", "| parameter | median sigma | unit |", "|---|---|---|"]
        lines += [f"| {n} | {_fmt(s['sigma_median'][n])} | {PARAM_UNITS[n]} |" for n in PARAM_NAMES]
    if ev.pulls is not None:
        lines += ["", "## Against the simulation truth", "",
                  f"Pulls (fit - truth)/sigma over {len(ev.pull_ids)} detectors; all 15 parameters within 3 sigma "
                  f"for {100 * s['all_within_3sigma_fraction']:.1f}% of detectors.", "",
                  "| parameter | pull mean | pull std | within 3 sigma |", "|---|---|---|---|"]
        lines += [f"| {n} | {s['pull_mean'][n]:+.3f} | {s['pull_std'][n]:.3f} | {100 * s['within_3sigma_fraction'][n]:.1f}% |"
                  for n in PARAM_NAMES]
        lines += ["", "![pulls](pulls.png)"]
    if ev.eps_arctan:
        req = REQUIREMENT_PER_PW
        lines += ["", "## End to end: effective nonlinearity", "",
                  f"Each true detector sees a HWP 2f signal of A = {s['hwp_amplitude_pw']:.2g} pW on its nominal loading; "
                  f"its counts are converted by the `{ev.converter}` converter built from the FITTED parameters; "
                  "eps_eff = 4 a4 / A^2 (a4: 4f amplitude of the reconstructed power).", "",
                  "| conversion | median abs(eps_eff) [1/pW] | max abs(eps_eff) [1/pW] | below 0.014 /pW by |", "|---|---|---|---|",
                  f"| MNTES, fitted arctan | {_fmt(s['eps_eff_median_per_pw'])} | {_fmt(s['eps_eff_max_per_pw'])} | x{_fmt(s['margin_factor'])} |"]
        if ev.eps_tabulated:
            lines.append(f"| MNTES, tabulated R(T) | {_fmt(s['eps_eff_tabulated_median_per_pw'])} | "
                         f"{_fmt(s['eps_eff_tabulated_max_per_pw'])} | x{_fmt(s['margin_factor_tabulated'])} |")
        lin = s["eps_eff_linear_median_per_pw"]
        lines.append(f"| linear conversion (for scale) | {_fmt(lin)} | | {'above' if lin > req else 'below'} (x{_fmt(lin / req)}) |")
        verdict = "meets" if s["eps_eff_max_per_pw"] < req else "does NOT meet"
        lines += ["", f"The fitted calibration {verdict} the 0.014 /pW requirement on every usable detector: the worst "
                      f"detector is a factor {_fmt(s['margin_factor'])} below it.", "", "![nonlinearity](nonlinearity.png)"]
    path = out / "summary.md"
    path.write_text("\n".join(lines) + "\n")
    return path


"""The leakage figure: per detector, the effective nonlinearity of the linear conversion and of MNTES."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mntes_stream.reports.plots import pyplot

__all__ = ["figure_leakage"]


def figure_leakage(res: dict, path: str | Path) -> None:
    """Draw ``mntes-stream leakage``'s result (its JSON dict) to a PNG.

    Per detector (x) the linear conversion's |eps| against MNTES and, where a truth was
    given, MNTES's against the truth, with 1-sigma bars; an unresolved value is drawn
    as its 3-sigma upper limit ``|nl| + 3 sigma`` (open triangle). The requirement is the dotted line.
    """
    plt = pyplot()
    rows = [r for r in res["detectors"] if r.get("status") == "ok"]
    fig, ax = plt.subplots(figsize=(max(6.0, min(16.0, 0.08 * len(rows) + 5)), 4.2))
    x = np.arange(len(rows))
    series = (("linear", "linear conversion (vs MNTES, same counts)", "C1"),
              ("mntes", "MNTES (vs simulator truth)", "C0"))
    for key, label, color in series:
        v, s, b = (np.array([np.nan if r.get(f"{key}_nl{k}_per_pw") is None else r[f"{key}_nl{k}_per_pw"]
                             for r in rows]) for k in ("", "_sigma", "_bound"))
        got, lim = np.isfinite(v), np.isfinite(b)
        if got.any():
            ax.errorbar(x[got], v[got], yerr=s[got], fmt="o", ms=3, color=color, label=label)
        if lim.any():
            ax.plot(x[lim], b[lim], "v", mfc="none", ms=4, color=color,
                    label=f"{label.split(' (')[0]}: not resolved, 3-sigma limit")
    ax.axhline(res["requirement_per_pw"], ls=":", color="k", lw=1,
               label=f"requirement {res['requirement_per_pw']} pW$^{{-1}}$")
    ax.set_yscale("log")
    ax.set_xlabel("detector (in stream order)")
    ax.set_ylabel("effective nonlinearity |f''/f'| [pW$^{-1}$]")
    f = res["f_hwp_hz"]
    ax.set_title(f"2f -> 4f leakage: f_HWP {f:.4g} Hz ({res['f_hwp_source']}), window {res['window_s']:.0f} s, "
                 f"{len(rows)} detectors" if f else "no 2f line to measure", fontsize=10)
    ax.legend(fontsize=8, loc="center right")
    ax.grid(alpha=0.3, which="both")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)

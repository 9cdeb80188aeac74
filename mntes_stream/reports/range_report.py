"""``mntes-stream validate --range``: the operating-range sweep's report (markdown, JSON, PNG)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from mntes_stream.core.sweep import REGIONS, RangeResult
from mntes_stream.reports.plots import pyplot

__all__ = ["summary_rows", "write_range_report", "figure_range"]

_COLORS = {"table": "C0", "grid": "C1", "exact": "C2", "linear": "C3", "electrical": "C4"}
_FLOOR_W = 1e-22  # where an exact zero is drawn on the log axis


def summary_rows(res: RangeResult) -> list[list[str]]:
    """Header plus one row per (model, kind): per region flagged fraction and worst unflagged error."""
    rows = [["model", "kind"] + [f"{r}: flagged / worst err" for r in REGIONS] + ["transition in-domain flagged"]]
    for model, kinds in res.stats.items():
        for kind, per in kinds.items():
            cells = []
            for region in REGIONS:
                st = per[region]
                cells.append("-" if not st["n"] else
                             f"{100 * st['flagged_frac']:.3g}% / {st['worst_unflagged_error_w']:.2g} W")
            tr = per["transition"]
            cells.append(f"{100 * tr['flagged_frac_in_domain']:.3g}% of {tr['n_in_domain']}")
            rows.append([model, kind] + cells)
    return rows


def figure_range(res: RangeResult, path) -> None:
    """|error| against P_opt per transition model; flagged samples as grey crosses (at their |error| or the top)."""
    plt = pyplot()
    models = list(res.samples)
    fig, axes = plt.subplots(len(models), 1, figsize=(10, 3.6 * len(models)), sharex=True, squeeze=False)
    for ax, model in zip(axes[:, 0], models):
        s = res.samples[model]
        p_pw = s["p_opt_w"] * 1e12
        top = 1e-10
        for kind, d in s.items():
            if kind in ("p_opt_w", "region"):
                continue
            err = np.abs(d["error_w"])
            fl = d["flagged"]
            shown = np.where(np.isfinite(err), np.maximum(err, _FLOOR_W), top)
            ax.plot(p_pw[~fl], shown[~fl], ".", ms=2, color=_COLORS.get(kind, "k"), label=f"{kind} (unflagged)")
            if kind == "table":
                ax.plot(p_pw[fl], np.minimum(shown[fl], top), "x", ms=3, color="0.6", alpha=0.5,
                        label="flagged (table kind; NaN drawn at the top)")
        ax.axhline(1e-17, color="k", lw=0.8, ls="--", label="1e-17 W")
        ax.set_yscale("log")
        ax.set_ylim(_FLOOR_W / 2, top * 3)
        ax.set_ylabel("|P_conv - P_ref| [W]")
        ax.set_title(f"{model}: P_opt 0-3 P_sat, T_bath 90-110 mK, |B| <= 200 uT, bias 0.25-1.05; int32 counts, readout noise")
        ax.legend(fontsize=7, ncol=3, loc="center right")
    axes[-1, 0].set_xlabel("true optical power P_opt [pW]")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def write_range_report(res: RangeResult, out_dir) -> dict:
    """Write ``range_report.md``, ``range_summary.json`` and ``range_errors.png`` into ``out_dir``."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    png = out / "range_errors.png"
    figure_range(res, png)
    (out / "range_summary.json").write_text(json.dumps(res.stats, indent=2))
    rows = summary_rows(res)
    md = ["# Fidelity over the operating range", "",
          "Error = converted power minus the model's power for the measured counts (truth on the branch) "
          "or minus the true P_opt (truth normal, latched or superconducting). 'flagged' = no value "
          "(UNUSABLE), PHASE_RESIDUAL or NONLINEAR (baselines: off the exact inverse by more than "
          "their tolerance, 1e-17 W).", "",
          "| " + " | ".join(rows[0]) + " |", "|" + "---|" * len(rows[0])]
    md += ["| " + " | ".join(r) + " |" for r in rows[1:]]
    md += ["", f"![errors]({png.name})", ""]
    (out / "range_report.md").write_text("\n".join(md))
    return {"report": str(out / "range_report.md"), "summary": str(out / "range_summary.json"), "figure": str(png)}

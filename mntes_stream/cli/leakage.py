"""``mntes-stream leakage REC``: the HWP 2f -> 4f nonlinearity MNTES removed, per detector, on a recording.

The recorded counts are converted twice in process with the live converter's
code (``pipeline.offline.convert_recording``, into a temporary directory):
with the recording's MNTES kind and with ``linear``, the linear baseline of
the same counts. ``core.leakage.leakage_between`` then measures, per
detector, the linear conversion's effective nonlinearity against MNTES
(readout noise and any optical 4f line cancel in the difference) and, with
the simulator's truth (``--truth``), MNTES's own residual against it.
"""

from __future__ import annotations

import json
import math

_BASELINES = ("linear", "electrical")


def _f_hwp(t_s, rows, given: float | None) -> tuple[float | None, str]:
    """f_HWP: given, else the monitor's spectral estimate refined on the 2f line; None when there is no comb."""
    import numpy as np

    from mntes_stream.core.leakage import refine_f_hwp

    if given is not None:
        return given, "given"
    from mntes_stream.monitor.analysis import estimate_f_hwp, welch_psd

    good = rows[np.mean(np.isfinite(rows), axis=1) > 0.9][:64]
    if not good.size:
        return None, "no usable power"
    fs_hz = 1.0 / float(np.median(np.diff(t_s)))
    f_hz, psd = welch_psd(good, fs_hz, segments=1)
    coarse = estimate_f_hwp(f_hz, psd)
    if coarse is None:
        return None, "no HWP comb in the power spectrum"
    return refine_f_hwp(t_s, good, coarse), "estimated"


def _truth_rows(truth: dict, detectors, t_ns):
    """The truth's optical power on the power's sample times (NaN where it has none), shape (n_det, n)."""
    import numpy as np

    ids = {str(d): i for i, d in enumerate(truth["detector_ids"])}
    tt = truth["t_ns"]
    k = np.clip(np.searchsorted(tt, t_ns), 0, tt.size - 1)
    hit = tt[k] == t_ns
    out = np.full((len(detectors), t_ns.size), np.nan)
    for j, d in enumerate(detectors):
        if d in ids:
            out[j, hit] = truth["truth_p_opt_w"][ids[d], k[hit]]
    return out


def _bound(r):
    """A 3-sigma upper limit on |nl| (pW^-1) where the value is not resolved, else None."""
    if r.nl_per_w is None or r.resolved:
        return None
    return _num(abs(r.nl_per_pw) + 3 * r.sigma_nl_per_pw, 3)


def _num(x, digits=6):
    return None if x is None or not math.isfinite(x) else float(f"{x:.{digits}g}")


def measure(rec, *, truth_path=None, f_hwp_hz=None, params=None, progress=False) -> dict:
    """Convert ``rec`` twice (MNTES, linear) and measure every detector; a JSON-ready dict."""
    import tempfile
    from pathlib import Path

    import numpy as np

    from mntes_stream.core import flags
    from mntes_stream.core.leakage import REQUIREMENT_PER_PW, leakage_between, median_nl
    from mntes_stream.errors import ConfigError
    from mntes_stream.feeds.recorded import RecordedPower
    from mntes_stream.pipeline.offline import convert_recording
    from mntes_stream.service.simulator import load_truth

    truth = load_truth(truth_path) if truth_path else None
    with tempfile.TemporaryDirectory(prefix="mntes-leakage-") as tmp:
        mntes_out = Path(tmp) / "mntes.mcap"
        stats = convert_recording(rec, mntes_out, params=params, progress=progress)
        mntes_kind = stats.converter_kind
        if mntes_kind in _BASELINES:  # a recording made with a baseline: MNTES is the reference here
            mntes_out.unlink()
            mntes_kind = convert_recording(rec, mntes_out, params=params, progress=progress, kind="table").converter_kind
        # Detectors the linear baseline cannot take (latched) come out NaN + UNKNOWN_CHANNEL (pipeline.build: drop_untaken).
        convert_recording(rec, Path(tmp) / "linear.mcap", params=params, progress=progress, kind="linear")
        mntes = RecordedPower(mntes_out).read()
        linear = RecordedPower(Path(tmp) / "linear.mcap").read()
    streams = sorted(set(mntes) & set(linear))
    if not streams:
        raise ConfigError(f"{rec}: no power came out of the recording's counts")
    t0_ns = min(int(mntes[s].t_ns[0]) for s in streams if mntes[s].t_ns.size)
    per_stream, no_baseline = [], set()
    for s in streams:
        m, lin = mntes[s], linear[s]
        common, im, il = np.intersect1d(m.t_ns, lin.t_ns, return_indices=True)
        rows_l = {d: j for j, d in enumerate(lin.detectors)}
        dets = list(m.detectors)
        p_m = np.asarray(m.p_opt_w)[[m.detectors.index(d) for d in dets]][:, im]
        p_l = np.full(p_m.shape, np.nan)
        for j, d in enumerate(dets):
            if d in rows_l:
                p_l[j] = np.asarray(lin.p_opt_w)[rows_l[d], il]
                if np.all(np.asarray(lin.flags)[rows_l[d]] & flags.UNKNOWN_CHANNEL):
                    no_baseline.add(d)
            else:
                no_baseline.add(d)
        per_stream.append((s, dets, common, p_m, p_l))
    # One f_HWP for the recording (one HWP), from the longest stream.
    s, dets, t_ns, p_m, _ = max(per_stream, key=lambda x: x[2].size)
    f_hz, f_source = _f_hwp((t_ns - t0_ns) * 1e-9, p_m, f_hwp_hz)
    rows, lin_res, mn_res = [], [], []
    for s, dets, t_ns, p_m, p_l in per_stream:
        t_s = (t_ns - t0_ns) * 1e-9
        p_t = _truth_rows(truth, dets, t_ns) if truth is not None else None
        for j, d in enumerate(dets):
            row = {"detector": d, "stream": s}
            if d in no_baseline:
                row["status"] = "no_linear_baseline"  # latched: not in the transition at its nominal operating point
                rows.append(row)
                continue
            if f_hz is None:
                row["status"] = "no_2f_line"
                rows.append(row)
                continue
            lin_r = leakage_between(t_s, p_l[j], p_m[j], f_hz)
            lin_res.append(lin_r)
            row.update(status=lin_r.status, window_s=_num(lin_r.window_s), samples=lin_r.n_samples,
                       a2_w=_num(abs(lin_r.line_2f.amplitude_w)) if lin_r.line_2f else None,
                       linear_nl_per_pw=_num(abs(lin_r.nl_per_pw)) if lin_r.resolved else None,
                       linear_nl_signed_per_pw=_num(lin_r.nl_per_pw),
                       linear_nl_sigma_per_pw=_num(lin_r.sigma_nl_per_pw, 3), linear_nl_bound_per_pw=_bound(lin_r))
            if p_t is not None:
                mn_r = leakage_between(t_s, p_m[j], p_t[j], f_hz)
                mn_res.append(mn_r)
                row.update(mntes_status=mn_r.status,
                           mntes_nl_per_pw=_num(abs(mn_r.nl_per_pw)) if mn_r.resolved else None,
                           mntes_nl_signed_per_pw=_num(mn_r.nl_per_pw),
                           mntes_nl_sigma_per_pw=_num(mn_r.sigma_nl_per_pw, 3), mntes_nl_bound_per_pw=_bound(mn_r))
            rows.append(row)
    med_l, med_m = median_nl(lin_res), median_nl(mn_res)
    n_ok = sum(r.get("status") == "ok" for r in rows)
    out = {
        "recording": str(rec), "mntes_kind": mntes_kind, "f_hwp_hz": _num(f_hz, 8), "f_hwp_source": f_source,
        "window_s": _num(max((r.window_s for r in lin_res), default=float("nan"))),
        "requirement_per_pw": REQUIREMENT_PER_PW, "truth": str(truth_path) if truth_path else None,
        "detectors_total": len(rows), "detectors_measured": n_ok,
        "detectors_no_2f_line": sum(r.get("status") == "no_2f_line" for r in rows),
        "detectors_no_linear_baseline": len(no_baseline),
        "median_linear_nl_per_pw": _num(med_l.value_per_pw), "median_linear_nl_sigma_per_pw": _num(med_l.sigma_per_pw, 3),
        "median_linear_nl_bound_per_pw": None if med_l.resolved else _num(med_l.bound_per_pw, 3),
        "linear_detector_sigma_per_pw": _num(med_l.detector_sigma_per_pw, 3), "linear_resolved": med_l.n_resolved,
        "median_mntes_nl_per_pw": _num(med_m.value_per_pw), "median_mntes_nl_sigma_per_pw": _num(med_m.sigma_per_pw, 3),
        "median_mntes_nl_bound_per_pw": None if med_m.resolved else _num(med_m.bound_per_pw, 3),
        "mntes_detector_sigma_per_pw": _num(med_m.detector_sigma_per_pw, 3), "mntes_resolved": med_m.n_resolved,
        "detectors": rows,
    }
    out["message"] = _message(out)
    return out


def _message(res: dict) -> str:
    req = res["requirement_per_pw"]
    if res["detectors_measured"] == 0:
        why = res["f_hwp_source"] if res["f_hwp_hz"] is None else f"at 2 x {res['f_hwp_hz']:.5g} Hz"
        return (f"no 2f line to measure ({why}): {res['detectors_total']} detectors, no nonlinearity "
                "estimate (is the HWP turning?)")
    lines = [f"f_HWP {res['f_hwp_hz']:.6g} Hz ({res['f_hwp_source']}), window {res['window_s']:.1f} s, "
             f"{res['detectors_measured']} of {res['detectors_total']} detectors with a 2f line"]
    if res["median_linear_nl_per_pw"] is not None:
        lines.append(f"linear conversion (against MNTES, same counts): median {res['median_linear_nl_per_pw']:.3g} "
                     f"+- {res['median_linear_nl_sigma_per_pw']:.2g} pW^-1 (requirement {req})")
    else:
        lines.append(f"linear conversion: not resolved ({res['linear_resolved']} of {res['detectors_measured']} "
                     f"detectors; 1-sigma per detector {res['linear_detector_sigma_per_pw']:.2g} pW^-1)")
    if res["truth"] is None:
        lines.append("MNTES against the truth: no truth given (--truth NPZ from simulate); not measured")
    elif res["median_mntes_nl_per_pw"] is not None:
        lines.append(f"MNTES against the truth: median {res['median_mntes_nl_per_pw']:.3g} +- "
                     f"{res['median_mntes_nl_sigma_per_pw']:.2g} pW^-1 (requirement {req})")
    elif res["median_mntes_nl_bound_per_pw"] is not None:
        bound = res["median_mntes_nl_bound_per_pw"]
        verdict = "below" if bound < req else "not resolved against"
        lines.append(f"MNTES against the truth: median < {bound:.2g} pW^-1 (3 sigma, from {res['detectors_measured']} "
                     f"detectors; 1-sigma per detector {res['mntes_detector_sigma_per_pw']:.2g}, "
                     f"{res['mntes_resolved']} resolve theirs): {verdict} the requirement {req}")
    else:
        lines.append("MNTES against the truth: no detector measured")
    return "\n".join(lines)


def _table(res: dict) -> str:
    def cell(r, key):
        v, s, b = (r.get(f"{key}_nl{x}_per_pw") for x in ("", "_sigma", "_bound"))
        if v is not None:
            return f"{v:.4g} +- {s:.2g}"
        return f"< {b:.2g} (3 sigma)" if b is not None else "-"

    width = max([len(r["detector"]) for r in res["detectors"]] + [8]) + 2
    out = [f"{'detector':<{width}}{'status':<20}{'linear pW^-1':<22}MNTES vs truth pW^-1"]
    for r in res["detectors"]:
        out.append(f"{r['detector']:<{width}}{r['status']:<20}{cell(r, 'linear'):<22}{cell(r, 'mntes')}")
    return "\n".join(out)


def run(args) -> int:
    from mntes_stream.cli._common import claim_out

    if args.png:
        claim_out(args.png, args.overwrite, inputs=[args.recording])
    res = measure(args.recording, truth_path=args.truth, f_hwp_hz=args.f_hwp, params=args.params,
                  progress=not (args.quiet or args.json))
    if args.png:
        from mntes_stream.reports.leakage import figure_leakage

        figure_leakage(res, args.png)
        res["figure"] = str(args.png)
    if args.json:
        print(json.dumps(res, indent=2))
        return 0
    if not args.quiet and res["detectors_measured"]:
        print(_table(res))
    print(res["message"])
    if args.png:
        print(f"wrote {args.png}")
    return 0


def register(sub) -> None:
    from mntes_stream.cli._common import add_json, add_overwrite, add_quiet, arguments
    from mntes_stream.options import number

    p = sub.add_parser(
        "leakage", help="HWP 2f -> 4f nonlinearity per detector on a recording: linear conversion vs MNTES",
        description="Convert the recorded counts with MNTES and with the linear baseline (in process, the live "
                    "converter's code) and measure, per detector, the effective nonlinearity each leaves at "
                    "4 f_HWP from the 2 f_HWP line (docs/leakage.md): linear against MNTES and, with --truth, "
                    "MNTES against the simulator's truth. Where the noise is too large the uncertainty is stated "
                    "instead of a number; with no 2f line it says so.")

    def fill(p):
        p.add_argument("recording", metavar="REC", help="an MCAP recording: file or directory (from up, record or "
                                                        "simulate --out)")
        p.add_argument("--truth", metavar="NPZ", help="the simulator's per-sample truth (simulate --truth): also "
                                                      "MNTES's own residual against it")
        p.add_argument("--f-hwp", type=number(float, "Hz", gt=0), metavar="HZ", help="HWP rotation frequency (default: estimated from "
                                                                  "the power spectrum, as the monitor does)")
        p.add_argument("--params", metavar="FILE", help="detector parameter TOML instead of the recorded one "
                                                        "(a simulate recording: its .params.toml)")
        p.add_argument("--png", metavar="FILE", help="draw the figure: per detector, linear vs MNTES against "
                                                     "the 0.014 pW^-1 requirement")
        add_overwrite(p, "replace an existing --png file")
        add_json(p, "print the result as one JSON document")
        add_quiet(p)  # one meaning for every command (docs/cli.md); it took no help text
        p.set_defaults(func=run)

    arguments(p, fill)

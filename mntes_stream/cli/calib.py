"""``mntes-stream calib``: simulate a ground-calibration campaign, fit it, inspect it."""

from __future__ import annotations

import dataclasses
import json
import os
import sys
from pathlib import Path

from mntes_stream.options import number

_GRIDS = ("full", "small")


def _simulate(args) -> int:
    from mntes_stream.core.calib.simulate import FULL_GRID, SMALL_GRID, simulate_campaign
    from mntes_stream.errors import ConfigError
    from mntes_stream.io.calib_file import write_campaign, write_truth

    if args.truth and Path(args.truth).resolve() == Path(args.out).resolve():
        raise ConfigError("--truth must be a different file from --out")
    if args.truth and Path(args.truth).exists() and not args.force:
        raise ConfigError(f"{args.truth} exists (--overwrite replaces it)")
    grid = FULL_GRID if args.grid == "full" else SMALL_GRID
    campaign, truth = simulate_campaign(args.detectors, seed=args.seed, grid=grid, noise_a=args.noise_a,
                                        board=args.board, module=args.module)
    campaign.metadata["grid"] = args.grid
    n = write_campaign(args.out, campaign, overwrite=args.force)
    if args.truth:
        write_truth(args.truth, truth, {"campaign": str(args.out), "seed": args.seed, "noise_a": args.noise_a})
    n_pts = sum(len(s) for d in campaign.detectors.values() for s in d.sweeps)
    print(f"wrote {args.out}: {len(campaign)} detectors, {n} messages, {n_pts} points"
          + (f"; truth in {args.truth}" if args.truth else ""))
    return 0


def _info(args) -> int:
    from mntes_stream.core.calib.measurements import KINDS
    from mntes_stream.io.calib_file import read_campaign

    campaign = read_campaign(args.file)
    per_kind = {k: [0, 0] for k in KINDS}
    for det in campaign.detectors.values():
        for s in det.sweeps:
            per_kind[s.kind][0] += 1
            per_kind[s.kind][1] += len(s)
    missing = {d: sorted(set(KINDS) - det.kinds()) for d, det in campaign.detectors.items() if set(KINDS) - det.kinds()}
    info = {
        "file": str(args.file),
        "detectors": len(campaign),
        "metadata": campaign.metadata,
        "sweeps": {k: {"sweeps": v[0], "points": v[1]} for k, v in per_kind.items()},
        "orphans": campaign.orphans,
        "missing_measurements": missing,
    }
    if args.json:
        print(json.dumps(info, indent=2))
        return 0
    print(f"{args.file}: {len(campaign)} detectors; metadata {campaign.metadata}")
    for k, v in per_kind.items():
        print(f"  {k:<24s} {v[0]:>6d} sweeps {v[1]:>8d} points")
    for d, reason in campaign.orphans.items():
        print(f"  orphan {d}: {reason}")
    for d, kinds in missing.items():
        print(f"  {d}: missing {', '.join(kinds)}")
    return 0


def _fit(args) -> int:
    from tqdm import tqdm

    from mntes_stream.cli._common import claim_out
    from mntes_stream.core.calib.fit import FitOptions, tabulated_transition
    from mntes_stream.errors import ConfigError, MntesError
    from mntes_stream.io.calib_file import read_campaign, read_truth, write_covariance, write_fit_params
    from mntes_stream.reports.calib_run import fit_campaign

    out = Path(args.out)
    cov_path = Path(args.covariance) if args.covariance else out.with_suffix(".cov.json")
    claim_out(out, args.overwrite, inputs=[args.file, *([args.truth] if args.truth else [])])
    campaign = read_campaign(args.file)
    truth = read_truth(args.truth) if args.truth else None
    if truth is not None:
        unknown = sorted(set(campaign.detectors) - set(truth))
        if unknown:
            raise ConfigError(f"--truth {args.truth} has no detector(s) {unknown[:5]} of {args.file} (mismatched ids)")
    workers = max(1, min(args.workers, len(campaign.detectors)))
    fits = fit_campaign(
        campaign, FitOptions(max_nfev=args.max_nfev), workers=workers,
        progress=lambda it, total: tqdm(it, total=total, desc="calib fit", unit="det", disable=args.quiet, file=sys.stderr),
    )
    # The parameter file carries the chosen transition; detectors whose table
    # cannot be built are flagged rather than silently given the arctan.
    arctan = {d: f.params for d, f in fits.items() if f.ok}
    tabulated, tab_problems = {}, {}
    for d, f in fits.items():
        if not f.ok:
            continue
        try:
            tabulated[d] = f.params.replace(transition=tabulated_transition(f))
        except (MntesError, ValueError) as exc:
            tab_problems[d] = f"tabulated transition: {exc}"
    if args.transition == "tabulated":
        for d, reason in tab_problems.items():
            f = fits[d]
            fits[d] = dataclasses.replace(f, status="flagged", reasons=f.reasons + (reason,))
    chosen = arctan if args.transition == "arctan" else tabulated
    write_fit_params(out, fits, chosen, args.transition, source=str(args.file))
    write_covariance(cov_path, fits)
    summary = {
        "file": str(args.file),
        "params": str(out),
        "covariance": str(cov_path),
        "transition": args.transition,
        "detectors": len(fits),
        "ok": sum(f.status == "ok" for f in fits.values()),
        "flagged": {d: list(f.reasons) for d, f in fits.items() if f.status == "flagged"},
        "failed": {d: list(f.reasons) for d, f in fits.items() if f.status == "failed"},
    }
    if truth is not None or args.report:
        from mntes_stream.reports.calib_report import evaluate, write_report

        ev = evaluate(campaign, fits, arctan, tabulated, truth, converter_kind=args.converter)
        summary.update(ev.summary)
        if args.report:
            summary["report"] = str(write_report(args.report, campaign, fits, ev, params_path=out))
    if args.json:
        print(json.dumps(summary, indent=2, default=str))
        return 0
    print(f"fitted {summary['detectors']} detectors: {summary['ok']} ok, {len(summary['flagged'])} flagged, "
          f"{len(summary['failed'])} failed -> {out} ({args.transition}), covariance {cov_path}")
    for d, reasons in {**summary["flagged"], **summary["failed"]}.items():
        print(f"  {d}: {'; '.join(reasons)}")
    if "eps_eff_max_per_pw" in summary:
        print(f"end to end ({summary['converter']} converter, HWP 2f A = {summary['hwp_amplitude_pw']} pW): "
              f"max |eps_eff| = {summary['eps_eff_max_per_pw']:.2e} /pW (arctan), "
              f"{summary['eps_eff_tabulated_max_per_pw']:.2e} /pW (tabulated); requirement 0.014 /pW")
    if "report" in summary:
        print(f"report: {summary['report']}")
    return 0


def _lab(args) -> int:
    """The lab's IV/bias-step results (sotodlib det_cal) against the parameters: disagreement, optionally seeded."""
    from mntes_stream.cli._common import claim_out
    from mntes_stream.core.calib.lab import compare, seed, table
    from mntes_stream.errors import ConfigError
    from mntes_stream.io.paramfile import dump_params, load_params
    from mntes_stream.io.sotodlib_cal import load_det_cal

    id_map = None
    if args.id_map:
        try:
            id_map = json.loads(Path(args.id_map).read_text())
        except (OSError, ValueError) as exc:
            raise ConfigError(f"{args.id_map}: cannot read the id map (JSON readout_id -> detector id): {exc}") from None
        if not isinstance(id_map, dict):
            raise ConfigError(f"{args.id_map}: expected a JSON object readout_id -> detector id")
    if args.seed_out:
        claim_out(args.seed_out, args.overwrite, inputs=(args.params, args.file))
    params = load_params(args.params)
    labs = load_det_cal(args.file, args.dataset, id_map)
    both = sorted(set(params) & set(labs))
    if not both:
        raise ConfigError(f"{args.file} [{args.dataset}] names none of the {len(params)} detectors of {args.params}")
    per = {d: compare(params[d], labs[d]) for d in both}
    out = {"source": f"{args.file} [{args.dataset}]", "detectors": len(both),
           "lab_only": len(set(labs) - set(params)), "params_only": len(set(params) - set(labs)),
           "summary": table(per), "per_detector": per if args.json else None}
    if args.seed_out:
        seeded = {d: seed(params[d], labs[d]) if d in labs else params[d] for d in params}
        dump_params(list(seeded.values()), args.seed_out,
                    metadata={"source": f"{args.params} seeded from the lab's {out['source']} (R_n, K from P_sat)"})
        out["seeded"] = args.seed_out
    if args.json:
        print(json.dumps(out, indent=1))
        return 0
    print(f"{out['source']}: {len(both)} detectors compared ({out['lab_only']} only in the lab's file, "
          f"{out['params_only']} only in {args.params})")
    for k, v in out["summary"].items():
        print(f"  {k:10s} median (MNTES - lab)/lab {v['median_rel_diff']:+.3g}, largest |.| "
              f"{v['max_abs_rel_diff']:.3g} ({v['n']} detectors)")
    if args.seed_out:
        print(f"wrote {args.seed_out}")
    return 0


def register(sub) -> None:
    from mntes_stream.cli._common import add_json, add_overwrite, add_quiet, deprecated_alias

    p = sub.add_parser("calib", help="ground calibration: simulate a campaign, fit per-detector parameters")
    csub = p.add_subparsers(dest="calib_command", metavar="ACTION", required=True)

    s = csub.add_parser("simulate", help="write a simulated calibration campaign (MCAP) and its truth (TOML)")
    s.add_argument("--detectors", type=number(int, ge=1), default=100, metavar="N", help="number of detectors (default 100)")
    s.add_argument("--seed", type=number(int, ge=0), default=0, help="random seed (default 0)")
    s.add_argument("--out", required=True, metavar="MCAP", help="campaign file to write")
    s.add_argument("--truth", metavar="TOML", help="write the true parameters here (marked as truth)")
    s.add_argument("--grid", choices=_GRIDS, default="full", help="points per sweep: full (default) or small")
    s.add_argument("--noise-a", type=number(float, "A", ge=0), default=1e-10, metavar="A",
                   help="noise of each of I and Q per point, in amperes (default 1e-10)")
    s.add_argument("--board", type=number(int, ge=0), default=0, help="board of the simulated detectors (default 0)")
    s.add_argument("--module", type=number(int, ge=0), default=0, help="module of the simulated detectors (default 0)")
    s.add_argument("--overwrite", dest="force", action="store_true", help="replace existing --out and --truth files")
    deprecated_alias(s, "--force", "--overwrite", dest="force", action="store_true")
    s.set_defaults(func=_simulate)

    f = csub.add_parser("fit", help="fit every detector of a campaign; write a parameter file")
    f.add_argument("file", metavar="FILE", help="campaign file (MCAP)")
    f.add_argument("--out", required=True, metavar="PARAMS.toml", help="parameter file to write (load_params reads it)")
    f.add_argument("--transition", choices=("arctan", "tabulated"), default="arctan",
                   help="transition written to the parameter file (default arctan)")
    f.add_argument("--covariance", metavar="JSON", help="covariance sidecar (default: PARAMS.cov.json)")
    f.add_argument("--report", metavar="DIR", help="write fit-quality PNGs and summary.md here")
    f.add_argument("--truth", metavar="TOML", help="truth of a simulated campaign: pulls and end-to-end nonlinearity")
    f.add_argument("--converter", default="table", choices=("table", "exact"),
                   help="converter for the end-to-end check (default table)")
    f.add_argument("--workers", type=number(int, ge=1), default=min(2, os.cpu_count() or 1), help="worker processes (default 2)")
    f.add_argument("--max-nfev", type=number(int, ge=1), default=200, help="model evaluations per fit before giving up")
    add_overwrite(f, "replace an existing --out file (and its covariance sidecar)")
    add_json(f, "print a JSON summary")
    add_quiet(f)
    f.set_defaults(func=_fit)

    lab = csub.add_parser("lab", help="the lab's IV and bias-step results (sotodlib det_cal HDF5) against the "
                                      "parameters: disagreement per quantity; --seed-out seeds R_n and K from them")
    lab.add_argument("file", metavar="DET_CAL.h5", help="sotodlib det_cal HDF5 (update_det_cal's output)")
    lab.add_argument("--dataset", required=True, metavar="OBS_ID", help="the dataset (observation id) in it")
    lab.add_argument("--params", required=True, metavar="PARAMS.toml", help="detector parameters to check")
    lab.add_argument("--id-map", metavar="JSON", help="readout_id -> detector id (default: the ids are ours)")
    lab.add_argument("--seed-out", metavar="PARAMS.toml", help="write the parameters seeded from the lab here")
    add_overwrite(lab, "replace an existing --seed-out file")
    add_json(lab, "print the comparison (per detector too) as JSON")
    lab.set_defaults(func=_lab)

    i = csub.add_parser("info", help="what a campaign file holds")
    i.add_argument("file", metavar="FILE", help="campaign file (MCAP)")
    add_json(i, "print one JSON object")
    i.set_defaults(func=_info)


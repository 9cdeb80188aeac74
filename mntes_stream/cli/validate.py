"""``mntes-stream validate``: the MNTES-versus-linear validation study, report and figures."""

from __future__ import annotations

import json

from mntes_stream.core.timing import DFMUX_SAMPLE_RATE_HZ
from mntes_stream.options import number


def run_range(args) -> int:
    """The operating-range sweep: every transition model and conversion kind, per region."""
    from mntes_stream.core.sweep import range_sweep
    from mntes_stream.reports.range_report import summary_rows, write_range_report

    def progress(step):
        if not args.json:
            print(f"range: {step}", flush=True)

    res = range_sweep(n_samples=args.samples, seed=args.seed, progress=progress)
    paths = write_range_report(res, args.out)
    noise = None
    if args.readout_noise > 0:
        from mntes_stream.core.sweep import noise_sweep

        noise = noise_sweep(n_samples=args.samples, readout_noise_a=args.readout_noise, seed=args.seed,
                            progress=progress)
    if args.json:
        print(json.dumps({"stats": res.stats, "noise": noise, "report": paths}, indent=2))
        return 0
    rows = summary_rows(res)
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    for r in rows:
        print("  ".join(c.ljust(w) for c, w in zip(r, widths)))
    if noise:
        print(f"\nwith {noise['readout_noise_a']:.3g} A readout noise declared, against the true power:")
        for name, kinds in noise["models"].items():
            for kind, d in kinds.items():
                print(f"  {name}/{kind}: worst unflagged {d['worst_unflagged_error_w']:.2g} W, "
                      f"{d['unflagged_beyond_bound']} beyond max(1e-17 W, 7 sigma_P), transition flagged "
                      f"{d['transition_flagged_frac']:.1%} (R 0.2-0.8 R_n: {d['mid_transition_flagged_frac']:.2%})")
    print(f"wrote {paths['report']}, {paths['summary']} and {paths['figure']}")
    return 0


def run(args) -> int:
    if args.range:
        return run_range(args)
    from tqdm import tqdm

    from mntes_stream.core.sim import HWP_FREQUENCIES_HZ
    from mntes_stream.core.validation import JSON_KEYS, StudyConfig, run_study
    from mntes_stream.reports.validation_report import headline_rows, to_jsonable, write_report

    opts = {"seed": args.seed, "sample_rate_hz": args.sample_rate, "f_hwp_hz": HWP_FREQUENCIES_HZ[args.telescope]}
    cfg = StudyConfig.quick_config(**opts) if args.quick else StudyConfig(**opts)
    steps = ["hwp", "spectra", "jupiter", "dipole", "drift", "robustness"]
    with tqdm(total=len(steps) + 1, desc="validate", unit="step", disable=args.json or None) as bar:
        def progress(step):
            bar.set_postfix_str(step)
            if step != steps[0]:
                bar.update(1)

        result = run_study(cfg, progress=progress)
        bar.update(1)
        bar.set_postfix_str("report")
        paths = write_report(result, args.out)
        bar.update(1)
    summary = result.summary
    if args.json:
        out = {k: summary[k] for k in JSON_KEYS}
        out.update({k: v for k, v in summary.items() if k not in out})
        out["report"] = paths
        print(json.dumps(to_jsonable(out), indent=2))
        return 0
    rows = headline_rows(summary)
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    for r in rows:
        print("  ".join(c.ljust(w) for c, w in zip(r, widths)))
    rob = summary["robustness"]["all_together"]
    print(f"\nrobustness (all calibration errors at the assumed levels, {rob['draws']} draws): "
          f"median {rob['median_per_pw']:.3g} /pW, 95% {rob['p95_per_pw']:.3g} /pW "
          f"(requirement {summary['requirement_per_pw']} /pW)")
    print(f"wrote {paths['report']} and {len(paths['figures'])} figures")
    return 0


def register(sub) -> None:
    p = sub.add_parser("validate", help="simulate, convert with MNTES and the linear baseline, report every effect")
    p.add_argument("--quick", action="store_true", help="shorter runs and fewer draws (well under a minute)")
    p.add_argument("--out", default="validation", metavar="DIR", help="report directory (default: ./validation)")
    p.add_argument("--json", action="store_true", help="print the results as one JSON object")
    p.add_argument("--seed", type=number(int, ge=0), default=0, help="simulation seed")
    p.add_argument("--telescope", choices=["LFT", "MFT", "HFT"], default="LFT",
                   help="HWP frequency: LFT 0.77, MFT 0.65, HFT 1.02 Hz (default LFT)")
    p.add_argument("--sample-rate", type=number(float, "Hz", gt=0), default=DFMUX_SAMPLE_RATE_HZ, metavar="HZ",
                   help=f"default {DFMUX_SAMPLE_RATE_HZ} (DfMux ground, 20 MHz / 2**17); 19.1 is flight-like")
    p.add_argument("--range", action="store_true",
                   help="instead: sweep P_opt 0-3 P_sat, bath, field and bias for every transition model and "
                        "conversion kind; flagged fraction and worst unflagged error per region, and a PNG")
    p.add_argument("--samples", type=number(int, ge=2), default=60_000, help="--range: samples per transition model")
    p.add_argument("--readout-noise", type=number(float, "A", ge=0), default=2e-12, metavar="A",
                   help="--range: also sweep with this white readout noise per quadrature (A rms), declared to "
                        "the converters, with sigma_P and LOW_RESPONSIVITY; errors against the true power "
                        "(default 2e-12: 2 counts at 1e-12 A/count; 0 skips)")
    p.set_defaults(func=run)

"""``mntes-stream bench convert``: counts-to-power speed and accuracy.

A realistic block (default 512 detectors x 10,000 samples): heterogeneous
detectors (T_c, IQR, K, n, z, field coefficients, pickup, current
dependence and gain phase all scattered), optical power 0.05-1.0 pW, bath
temperature and field varying every sample, biases at +-5% states, and 0.1% of
the samples invalid (counts at the int32 rail) so the flag path is exercised.

Speed is the median of repeated full conversions (wall clock, and CPU time
of this process, which is less disturbed by other load on a shared machine),
beside numpy's ``a * x + b`` over the same counts array in the same run; and
over live-size chunks (128 detectors x 20 samples, ``chunks_cpu_msamples_per_s``),
where per-call and per-row costs count, converter call included.
Accuracy is against the exact per-sample inverse on the same counts.

LOW_RESPONSIVITY is on by default (``[converter] low_responsivity``): the
conversion with it (``core.uncertainty.low_responsivity_block``, flagged in
the kernel's own pass) and without it are timed in back-to-back pairs in the
same run, ``low_responsivity.cost_ratio`` the median of the pairs' CPU-time
ratios (``cost_ratios`` each pair's; ``chunks_cost_ratio`` on live-size
chunks, pairs of 50 chunks); its flags are checked against
the full sigma_P pass's on the whole block. ``flagged_samples`` are the
default's (with LOW_RESPONSIVITY).

The baselines (``linear``, ``electrical``) are timed the same way, with their
ratio to ``a * x + b``: alone (``tolerance_w=None``), with the default
``NONLINEAR`` check (from a table bank) and with the check by the exact
inverse, on the whole block and on live-size chunks (128 x 20).
"""

from __future__ import annotations

import time

import numpy as np

HELP = "table conversion: Msamples/s vs numpy axpy, accuracy vs the exact inverse, build time, bank size"

_BIAS_STATES = (0.95, 1.0, 1.05)


def add_arguments(p) -> None:
    p.add_argument("--detectors", type=int, default=512, help="detectors to convert (default 512)")
    p.add_argument("--samples", type=int, default=10_000, help="samples per detector (default 10000)")
    p.add_argument("--repeats", type=int, default=7, help="timed conversions (median reported)")
    p.add_argument("--build-detectors", type=int, default=1000, help="detectors in the build-time measurement")
    p.add_argument("--quick", action="store_true", help="small sizes for a smoke run (64 x 2000, 3 repeats)")
    p.add_argument("--no-numpy", action="store_true", help="skip timing the numpy backend")
    p.add_argument("--png", metavar="FILE", help="write a figure of the errors against the exact inverse")
    p.add_argument("--seed", type=int, default=3, help="random seed (default 3)")
    p.add_argument("--range", action="store_true",
                   help="also the operating-range sweep (core.sweep): per kind, worst unflagged error over every "
                        "region and transition model, and the transition's flagged fraction")
    p.add_argument("--range-samples", type=int, default=20_000, help="--range: samples per transition model")
    p.add_argument("--uncertainty", action="store_true",
                   help="also time sigma_P and LOW_RESPONSIVITY (core.uncertainty, its compiled pass) on the same "
                        "block, and the conversion with it")


def synthetic_params(n_det: int, seed: int = 0, start: int = 0) -> dict:
    """Heterogeneous Table-1-like detectors, bias tuned to R = 0.7 R_n at 0.5 pW."""
    from mntes_stream.core import model
    from mntes_stream.core.ids import detector_id
    from mntes_stream.core.params import table1_params

    rng = np.random.default_rng(seed)
    out = {}
    for k in range(start, start + n_det):
        p = table1_params(
            detector_id(k // 512, (k // 128) % 4, k % 128),
            t_c_k=0.180 * (1 + rng.normal(0, 0.01)),
            iqr_k=1.143e-3 * (1 + rng.normal(0, 0.1)),
            k_w_per_k_n=6.84e-10 * (1 + rng.normal(0, 0.03)),
            n=3.6 + rng.normal(0, 0.05),
            z_thev_ohm=complex(0.05 * (1 + rng.normal(0, 0.1)), 0.05 * (1 + rng.normal(0, 0.1))),
            t_c_shift_k_per_t=rng.normal(0, 0.2),
            t_c_shift_k_per_t2=rng.normal(0, 100.0),
            pickup_a_per_t=complex(*rng.normal(0, 1e-4, 2)),
            current_shift_k_per_a=abs(rng.normal(300.0, 100.0)),
            gain_a_per_count=1e-12 * np.exp(1j * rng.uniform(-np.pi, np.pi)),
        )
        out[p.detector_id] = p.replace(v_thev_v=float(model.tune_bias_v(p, 0.7)))
    return out


def tabulated_params(detector_id: str = "b0m0c100"):
    """A detector with a measured-looking R(T) (:func:`core.params.tabulated_example_params`)."""
    from mntes_stream.core.params import tabulated_example_params

    return tabulated_example_params(detector_id)


def synthetic_block(params: dict, n_samp: int, seed: int = 0, bad_fraction: float = 1e-3):
    """Counts and environment for ``params``: returns ``(ids, counts_i, counts_q, env)``."""
    from mntes_stream.core import model
    from mntes_stream.core.convert import EnvironmentBlock
    from mntes_stream.core.tables import TableDomain, resistance_range_ohm

    rng = np.random.default_rng(seed)
    plist = list(params.values())
    n_det = len(plist)
    s = np.arange(n_samp)
    tb = 0.100 + 0.004 * np.sin(2 * np.pi * s / 3001.0) + rng.normal(0, 2e-5, n_samp)
    b = 80e-6 * np.sin(2 * np.pi * s / 1303.0) + rng.normal(0, 2e-6, n_samp)
    v = np.array([p.v_thev_v for p in plist]) * rng.choice(_BIAS_STATES, n_det)
    ci = np.empty((n_det, n_samp), dtype=np.int32)
    cq = np.empty_like(ci)
    domain = TableDomain()
    for k, p in enumerate(plist):
        # Optical power 0.05-1 pW through the response at the nominal bath and zero field.
        r_lo, r_hi = resistance_range_ohm(p, domain)
        r_grid = np.linspace(r_lo, r_hi, 4000)
        p_grid = model.power_of_resistance_w(p, r_grid, p.t_bath_k, 0.0, v[k])
        r = np.interp(rng.uniform(0.05e-12, 1.0e-12, n_samp), p_grid, r_grid)
        i = model.readout_current_a(p, model.tes_current_a(p, r, v[k]), b) / p.gain_a_per_count
        ci[k] = np.rint(i.real)
        cq[k] = np.rint(i.imag)
    bad = rng.random(ci.shape) < bad_fraction
    ci[bad] = np.iinfo(np.int32).max
    return list(params), ci, cq, EnvironmentBlock(t_bath_k=tb, b_field_t=b, v_thev_v=v)


def _timed(fn, repeats: int) -> tuple[float, float]:
    """Median wall and CPU seconds of ``fn()``."""
    wall, cpu = [], []
    for _ in range(repeats):
        w0, c0 = time.perf_counter(), time.process_time()
        fn()
        wall.append(time.perf_counter() - w0)
        cpu.append(time.process_time() - c0)
    return float(np.median(wall)), float(np.median(cpu))


def _max_err(a: np.ndarray, ref: np.ndarray) -> float:
    both = np.isfinite(a) & np.isfinite(ref)
    return float(np.max(np.abs(a[both] - ref[both]))) if np.any(both) else float("nan")


def run(args) -> dict:
    from mntes_stream.core import flags as fl
    from mntes_stream.core.convert import make_converter
    from mntes_stream.core.tables import build_bank

    if args.quick:
        args.detectors, args.samples, args.repeats = min(args.detectors, 64), min(args.samples, 2000), min(args.repeats, 3)
        args.build_detectors = min(args.build_detectors, 100)
    n_det, n_samp = args.detectors, args.samples
    n = n_det * n_samp
    params = synthetic_params(n_det, seed=args.seed)
    ids, ci, cq, env = synthetic_block(params, n_samp, seed=args.seed + 1)

    # Build time on detectors not seen before (nothing cached).
    build_params = synthetic_params(args.build_detectors, seed=args.seed + 2, start=n_det)
    t0 = time.perf_counter()
    built = build_bank(build_params, kind="table")
    build_s = time.perf_counter() - t0

    bank = build_bank(params, kind="table")
    conv = make_converter("table", None, bank=bank, backend="auto")
    conv.convert(ids[:1], ci[:1, :10], cq[:1, :10], env.__class__(env.t_bath_k[:10], env.b_field_t[:10], env.v_thev_v[:1]))
    out = conv.convert(ids, ci, cq, env)
    wall, cpu = _timed(lambda: conv.convert(ids, ci, cq, env), args.repeats)
    axpy_wall, axpy_cpu = _timed(lambda: 1.5 * ci + 2.0, args.repeats)
    chunks_cpu = float(np.median([_live_chunks(conv, ids, ci, cq, env) for _ in range(3)]))

    exact = make_converter("exact", params)
    t0 = time.perf_counter()
    ref = exact.convert(ids, ci, cq, env)
    exact_s = time.perf_counter() - t0
    baselines, base_out = _baselines(make_converter, params, ids, ci, cq, env, args.repeats, n, axpy_wall)
    lin, ele = base_out["linear"], base_out["electrical"]

    result = {
        "detectors": n_det,
        "samples": n_samp,
        "backend": conv.backend,
        "msamples_per_s": n / wall / 1e6,
        "cpu_msamples_per_s": n / cpu / 1e6,
        "axpy_msamples_per_s": n / axpy_wall / 1e6,
        "ratio_to_axpy": axpy_wall / wall,
        "cpu_ratio_to_axpy": axpy_cpu / cpu,
        "chunks_cpu_msamples_per_s": chunks_cpu,
        "exact_msamples_per_s": n / exact_s / 1e6,
        "max_abs_error_w": _max_err(out.p_opt_w, ref.p_opt_w),
        "flags_identical_to_exact": bool(np.array_equal(out.flags, ref.flags)),
        "linear_max_abs_error_w": _max_err(lin.p_opt_w, ref.p_opt_w),
        "electrical_max_abs_error_w": _max_err(ele.p_opt_w, ref.p_opt_w),
        "flagged_samples": {k: v for k, v in fl.counts_by_flag(out.flags).items() if v},
        "build_s_per_1000_detectors": build_s * 1000.0 / args.build_detectors,
        "build_detectors": args.build_detectors,
        "build_bank_mib": built.nbytes / 2**20,
        "bank_bytes": bank.nbytes,
        "bank_mib_per_5000_detectors": bank.nbytes / n_det * 5000 / 2**20,
        "knots_per_detector_median": float(np.median(np.diff(bank.arrays["knot_offset"]))),
        "identity": bank.identity,
        **baselines,
    }
    if not args.no_numpy:
        conv_np = make_converter("table", None, bank=bank, backend="numpy")
        np_wall, _ = _timed(lambda: conv_np.convert(ids, ci, cq, env), max(1, min(args.repeats, 3)))
        result["numpy_msamples_per_s"] = n / np_wall / 1e6
        result["numba_speedup_over_numpy"] = np_wall / wall

    grid_bank = build_bank(params, kind="grid", bias_frac=_BIAS_STATES)
    grid = make_converter("grid", None, bank=grid_bank)
    grid.convert(ids, ci, cq, env)
    g_wall, _ = _timed(lambda: grid.convert(ids, ci, cq, env), args.repeats)
    g_out = grid.convert(ids, ci, cq, env)
    result.update({
        "grid_msamples_per_s": n / g_wall / 1e6,
        "grid_max_abs_error_w": _max_err(g_out.p_opt_w, ref.p_opt_w),
        "grid_bank_mib_per_5000_detectors": grid_bank.nbytes / n_det * 5000 / 2**20,
    })
    result["low_responsivity"] = low = _low_responsivity(conv, ids, ci, cq, env, out, args.repeats, n)
    result["flagged_samples"] = low.pop("flagged_samples")
    if getattr(args, "uncertainty", False):
        result["uncertainty"] = _uncertainty(conv, ids, ci, cq, env, out, args.repeats, n, cpu)
    if getattr(args, "range", False):
        result["range"] = range_summary(args.range_samples, seed=args.seed)
    if args.png:
        _figure(args.png, ref.p_opt_w, {"table": out.p_opt_w, "grid": g_out.p_opt_w, "linear": lin.p_opt_w,
                                        "electrical": ele.p_opt_w})
        result["figure"] = args.png
    return result


def _low_responsivity(conv, ids, ci, cq, env, block, repeats: int, n: int) -> dict:
    """The conversion with LOW_RESPONSIVITY (the default) against without, timed alternately (CPU seconds,
    medians), on the block and on live-size chunks; its flags against the full sigma_P pass's."""
    from mntes_stream.core import flags as fl
    from mntes_stream.core.uncertainty import low_responsivity_block, noise_model, sigma_p_block

    t0 = time.perf_counter()
    noise = noise_model(conv.params)
    build_s = time.perf_counter() - t0
    with_low = low_responsivity_block(conv, ids, ci, cq, env, noise)  # compiles, warms
    same = bool(np.array_equal(with_low.flags, sigma_p_block(conv, ids, ci, cq, env, block, noise).flags))
    # Pairs timed back to back share the machine's load: the figure is the median of the pairs' ratios. At
    # least 31 pairs (15 chunk rounds): on a shared 2-core machine single pairs scatter +-20 %, and the median
    # of 15 moved by ~0.03 between runs, as much as the effect measured.
    plain_cpu, low_cpu = [], []
    for _ in range(max(2 * repeats + 1, 31)):
        plain_cpu.append(_timed(lambda: conv.convert(ids, ci, cq, env), 1)[1])
        low_cpu.append(_timed(lambda: low_responsivity_block(conv, ids, ci, cq, env, noise), 1)[1])
    chunks_plain, chunks_low = [], []
    for _ in range(15):
        chunks_plain.append(_live_chunks(conv, ids, ci, cq, env))
        chunks_low.append(_live_chunks(conv, ids, ci, cq, env, noise=noise))
    p, lo = float(np.median(plain_cpu)), float(np.median(low_cpu))
    cp, cl = float(np.median(chunks_plain)), float(np.median(chunks_low))
    return {
        "cpu_msamples_per_s": n / lo / 1e6,
        "without_cpu_msamples_per_s": n / p / 1e6,
        "cost_ratio": float(np.median(np.array(low_cpu) / np.array(plain_cpu))),
        "cost_ratios": [round(float(x), 3) for x in np.array(low_cpu) / np.array(plain_cpu)],
        "chunks_cpu_msamples_per_s": cl,
        "chunks_without_cpu_msamples_per_s": cp,
        "chunks_cost_ratio": float(np.median(np.array(chunks_plain) / np.array(chunks_low))),
        "power_identical_to_without": bool(np.array_equal(with_low.p_opt_w, block.p_opt_w, equal_nan=True)),
        "flags_identical_to_sigma_p_pass": same,
        "samples_flagged": int(np.count_nonzero(with_low.flags & fl.LOW_RESPONSIVITY)),
        "noise_model_build_s": build_s,
        "flagged_samples": {k: v for k, v in fl.counts_by_flag(with_low.flags).items() if v},
    }


def _uncertainty(conv, ids, ci, cq, env, block, repeats: int, n: int, convert_cpu: float) -> dict:
    """sigma_P's own cost (core.uncertainty.sigma_p_block after the conversion), CPU seconds."""
    from mntes_stream.core import flags as fl
    from mntes_stream.core.uncertainty import noise_model, sigma_p_block

    t0 = time.perf_counter()
    noise = noise_model(conv.params)
    build_s = time.perf_counter() - t0
    unc = sigma_p_block(conv, ids, ci, cq, env, block, noise)
    _, cpu = _timed(lambda: sigma_p_block(conv, ids, ci, cq, env, block, noise), repeats)
    return {
        "sigma_p_cpu_msamples_per_s": n / cpu / 1e6,
        "convert_with_sigma_p_cpu_msamples_per_s": n / (convert_cpu + cpu) / 1e6,
        "sigma_p_cost_over_convert": cpu / convert_cpu,
        "noise_model_build_s": build_s,
        "low_responsivity_samples": int(np.count_nonzero(unc.flags & fl.LOW_RESPONSIVITY)),
    }


def _baselines(make_converter, params, ids, ci, cq, env, repeats: int, n: int, axpy_wall: float):
    """The baselines' speed: their arithmetic and flags alone (``tolerance_w=None``), beside
    ``a * x + b``; as configured by default (the ``NONLINEAR`` check on, from a table bank,
    the bank's build apart); and with the check by the exact inverse (timed once), whose
    flags the default's must equal.

    Returns the figures and each kind's default output (for the accuracy figures).
    """
    from mntes_stream.core.flags import NONLINEAR

    res, outs = {}, {}
    for kind in ("linear", "electrical"):
        bare = make_converter(kind, params, tolerance_w=None)
        bare.convert(ids, ci, cq, env)  # compile, warm
        wall, cpu = _timed(lambda: bare.convert(ids, ci, cq, env), repeats)
        t0 = time.perf_counter()
        checked = make_converter(kind, params)
        build_s = time.perf_counter() - t0
        outs[kind] = checked.convert(ids, ci, cq, env)
        c_wall, c_cpu = _timed(lambda: checked.convert(ids, ci, cq, env), max(1, min(repeats, 3)))
        exact = make_converter(kind, params, nonlinear_check="exact")
        w0 = time.perf_counter()
        by_exact = exact.convert(ids, ci, cq, env)
        e_wall = time.perf_counter() - w0
        chunk_cpu = {label: _live_chunks(c, ids, ci, cq, env) for label, c in
                     (("", bare), ("checked_", checked), ("exact_checked_", exact))}
        res.update({f"{kind}_{label}chunks_cpu_msamples_per_s": v for label, v in chunk_cpu.items()})
        res.update({
            f"{kind}_check_build_s": build_s,
            f"{kind}_exact_checked_msamples_per_s": n / e_wall / 1e6,
            f"{kind}_check_flags_identical_to_exact": bool(np.array_equal(outs[kind].flags, by_exact.flags)),
            f"{kind}_msamples_per_s": n / wall / 1e6,
            f"{kind}_cpu_msamples_per_s": n / cpu / 1e6,
            f"{kind}_ratio_to_axpy": axpy_wall / wall,
            f"{kind}_checked_msamples_per_s": n / c_wall / 1e6,
            f"{kind}_checked_cpu_msamples_per_s": n / c_cpu / 1e6,
            f"{kind}_checked_ratio_to_axpy": axpy_wall / c_wall,
            f"{kind}_nonlinear_frac": float(np.mean((outs[kind].flags & NONLINEAR) != 0)),
        })
    return res, outs


def _live_chunks(conv, ids, ci, cq, env, n_det: int = 128, n_samp: int = 20, n_chunks: int = 50,
                 noise=None) -> float:
    """M samples per CPU second over live-size chunks (128 detectors x 20 samples, as a stream
    delivers them), where per-call and per-row costs count; with ``noise``, LOW_RESPONSIVITY flagged."""
    from mntes_stream.core.uncertainty import low_responsivity_block

    n_det, width = min(n_det, ci.shape[0]), min(n_samp, ci.shape[1])
    spans = [(s, s + width) for s in range(0, ci.shape[1] - width + 1, width)][:n_chunks]
    blocks = [(ci[:n_det, a:b], cq[:n_det, a:b], env.__class__(env.t_bath_k[a:b], env.b_field_t[a:b],
                                                                  env.v_thev_v[:n_det])) for a, b in spans]
    c0 = time.process_time()
    if noise is None:
        for i, q, e in blocks:
            conv.convert(ids[:n_det], i, q, e)
    else:
        for i, q, e in blocks:
            low_responsivity_block(conv, ids[:n_det], i, q, e, noise)
    return n_det * width * len(blocks) / (time.process_time() - c0) / 1e6


def range_summary(n_samples: int, seed: int = 0) -> dict:
    """Per kind, over every transition model: worst unflagged error in any region and the largest
    flagged fraction of in-domain transition samples (:func:`core.sweep.range_sweep`)."""
    from mntes_stream.core.sweep import range_sweep

    t0 = time.perf_counter()
    res = range_sweep(n_samples=n_samples, seed=seed)
    out = {}
    for kinds in res.stats.values():
        for kind, per in kinds.items():
            o = out.setdefault(kind, {"worst_unflagged_error_w": 0.0, "transition_flagged_frac_in_domain": 0.0})
            o["worst_unflagged_error_w"] = max(o["worst_unflagged_error_w"],
                                               max(r["worst_unflagged_error_w"] for r in per.values()))
            o["transition_flagged_frac_in_domain"] = max(o["transition_flagged_frac_in_domain"],
                                                         per["transition"]["flagged_frac_in_domain"])
    return {"samples_per_model": n_samples, "models": list(res.stats), "by_kind": out,
            "elapsed_s": time.perf_counter() - t0}


def _figure(path: str, ref: np.ndarray, kinds: dict) -> None:
    from mntes_stream.reports.plots import pyplot

    plt = pyplot()
    rng = np.random.default_rng(0)
    pick = rng.choice(ref.size, size=min(ref.size, 8000), replace=False)
    x = ref.ravel()[pick] * 1e12
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    for name, marker in (("table", "."), ("grid", ".")):
        err = np.abs(kinds[name].ravel()[pick] - ref.ravel()[pick])
        axes[0].semilogy(x, np.maximum(err, 1e-24), marker, ms=1.5, alpha=0.5, label=name)
    axes[0].axhline(1e-19, color="k", lw=1, ls="--", label="1e-19 W target")
    axes[0].set(xlabel="optical power (pW)", ylabel="|P - P_exact| (W)", title="MNTES tables vs exact inverse")
    axes[0].legend(markerscale=6)
    for name in ("linear", "electrical"):
        err = kinds[name].ravel()[pick] - ref.ravel()[pick]
        axes[1].plot(x, err * 1e12, ".", ms=1.5, alpha=0.5, label=name)
    axes[1].set(xlabel="optical power (pW)", ylabel="P - P_exact (pW)", title="Baselines vs exact inverse")
    axes[1].legend(markerscale=6)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)

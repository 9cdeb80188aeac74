"""Fidelity over the whole operating range (``mntes-stream validate --range``): pure computation.

For each transition model (arctan, tabulated, current-dependent) one detector
is driven through P_opt from 0 to 3 P_sat (a triangle, so the latch's
history matters), bath temperature 90-110 mK and field +-200 uT across their
ranges, at biases on the grid kind's states and, for the latched and
bistable regions, at 0.25 and 0.5 of nominal. Truth from
:func:`core.model.solve_operating_point` (sequential: hysteresis), int32
counts with readout noise (``model.DEFAULT_READOUT_NOISE_A`` per quadrature).

The error of a sample is the converted power minus the reference: for a
detector truly on its positive-feedback branch (``STATE_TRANSITION``), the
model's power for the current the readout measured (readout noise and
quantisation are measurement, not conversion error); for a detector truly
off it (normal, latched, superconducting) the true P_opt: nothing it reads
means anything. Regions by truth: superconducting, latched, saturated
(normal, or R at or above the SATURATED threshold), transition (the rest),
except ``boundary``: a true R within the noise margin (``model.K_SIGMA``
sigma of R) of a SATURATED or LATCHED threshold, where either outcome is
right (the value, when given, must still be right). ``flagged_frac_in_domain``
counts only samples whose environment is inside the table domain (bias
0.9-1.1 of nominal): the under-biased segments are ENV_OUT_OF_RANGE there and
the table kinds cannot cover them.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from mntes_stream.core import flags as fl
from mntes_stream.core import model

__all__ = ["REGIONS", "RangeResult", "range_detectors", "range_samples", "range_sweep", "noise_sweep",
           "NOISE_SWEEP_READOUT_A"]

REGIONS = ("superconducting", "transition", "saturated", "latched", "boundary")


@dataclass(frozen=True)
class RangeResult:
    """Per model and kind: the sweep's samples and per-region figures.

    ``stats[model][kind][region]`` holds ``n``, ``flagged_frac`` and
    ``worst_unflagged_error_w`` (0 when every sample is flagged).
    ``samples[model]`` holds ``p_opt_w``, ``region`` (index into ``REGIONS``)
    and per kind ``error_w`` and ``flagged``.
    """

    stats: dict
    samples: dict = field(repr=False)


def range_detectors() -> dict:
    """The three transition models, each a Table-1 detector with field coefficients and pickup."""
    from mntes_stream.core.params import table1_params, tabulated_example_params

    common = {"t_c_shift_k_per_t": 2.0, "t_c_shift_k_per_t2": 1e4, "pickup_a_per_t": 2e-4 + 1e-4j,
              "gain_a_per_count": 1e-12 * np.exp(0.4j)}
    arctan = table1_params("b0m0c000", **common)
    current = table1_params("b0m0c001", current_shift_k_per_a=300.0, **common)
    tab = tabulated_example_params("b0m0c002").replace(gain_a_per_count=1e-12 * np.exp(-1.1j))
    out = {}
    for name, p in (("arctan", arctan), ("tabulated", tab), ("current-dependent", current)):
        out[name] = p.replace(v_thev_v=float(model.tune_bias_v(p, 0.7)))
    return out


def range_samples(p, n: int, seed: int = 0, readout_noise_a: float = model.DEFAULT_READOUT_NOISE_A):
    """Environment, truth and counts of one detector's sweep (arrays of shape (n_total,)).

    Three segments: the main sweep (bias on 0.95/1.0/1.05 of nominal), an
    under-biased one (0.25) and a bistable one (0.5), each a triangle in P_opt.
    ``readout_noise_a``: white noise per quadrature added to the current before quantisation.
    """
    rng = np.random.default_rng(seed)
    p_sat = float(p.p_sat_w)
    seg = []
    for frac, share in ((None, 0.7), (0.25, 0.15), (0.5, 0.15)):
        m = int(n * share)
        tri = 1.0 - np.abs(np.linspace(-1.0, 1.0, m))  # 0 -> 1 -> 0
        p_opt = 3.0 * p_sat * tri if frac is None else 1.5 * p_sat * tri
        tb = rng.uniform(0.090, 0.110, m)
        b = rng.uniform(-2e-4, 2e-4, m)
        vf = rng.choice([0.95, 1.0, 1.05], m) if frac is None else np.full(m, frac)
        seg.append((p_opt, tb, b, vf * p.v_thev_v))
    p_opt, tb, b, v = (np.concatenate(x) for x in zip(*seg))
    # One time stream per segment: the latch carries within it, each starts on its branch.
    ops = []
    start = 0
    for s in seg:
        m = s[0].size
        sl = slice(start, start + m)
        ops.append(model.solve_operating_point(p, p_opt[sl], tb[sl], b[sl], v[sl], sequential=True))
        start += m
    r = np.concatenate([o.r_ohm for o in ops])
    state = np.concatenate([o.state for o in ops])
    i_tes = np.concatenate([o.i_a for o in ops])
    sigma = readout_noise_a
    i_meas = model.readout_current_a(p, i_tes, b) + sigma * (rng.standard_normal(r.size) + 1j * rng.standard_normal(r.size))
    c = i_meas / p.gain_a_per_count
    ci = np.rint(c.real).astype(np.int32)
    cq = np.rint(c.imag).astype(np.int32)
    return {"p_opt_w": p_opt, "t_bath_k": tb, "b_field_t": b, "v_thev_v": v, "r_ohm": r, "state": state,
            "counts_i": ci, "counts_q": cq}


def _regions(p, s) -> np.ndarray:
    th = model.flag_thresholds(p)
    st = s["state"]
    r, v = s["r_ohm"], s["v_thev_v"]
    _, r_lat, r_sat = th.at_bias(v)
    sigma_r = th.sigma_i_a * np.abs(r + p.z_thev_ohm) ** 2 / (model.SQRT2 * v)
    reg = np.full(st.size, REGIONS.index("transition"))
    on = st == model.STATE_TRANSITION
    reg[(st == model.STATE_NORMAL) | (on & (r >= r_sat))] = REGIONS.index("saturated")
    reg[st == model.STATE_LATCHED] = REGIONS.index("latched")
    reg[st == model.STATE_SUPERCONDUCTING] = REGIONS.index("superconducting")
    near = (np.abs(r - r_sat) < model.K_SIGMA * sigma_r) | (np.abs(r - r_lat) < model.K_SIGMA * sigma_r)
    reg[(on | (st == model.STATE_LATCHED)) & near] = REGIONS.index("boundary")
    return reg


def range_sweep(n_samples: int = 60_000, kinds=("table", "grid", "exact", "linear", "electrical"), seed: int = 0,
                progress=None) -> RangeResult:
    """Run the sweep for every transition model and conversion kind.

    Parameters
    ----------
    n_samples : int
        Samples per detector (all segments).
    progress : callable(str), optional
        Called with ``"model/kind"`` before each conversion.
    """
    from mntes_stream.core.convert import EnvironmentBlock, make_converter
    from mntes_stream.core.tables import TableDomain, build_bank

    stats: dict = {}
    samples: dict = {}
    for k, (name, p) in enumerate(range_detectors().items()):
        s = range_samples(p, n_samples, seed + k)
        reg = _regions(p, s)
        # Reference: the model's power for the measured counts where the truth is on the branch.
        i_q = p.gain_a_per_count * (s["counts_i"] + 1j * s["counts_q"])
        with np.errstate(all="ignore"):
            inv = model.invert_current(p, i_q, s["t_bath_k"], s["b_field_t"], s["v_thev_v"])
        on_branch = s["state"] == model.STATE_TRANSITION
        ref = np.where(on_branch, inv.p_opt_w, s["p_opt_w"])
        ref = np.where(on_branch & np.isnan(ref), s["p_opt_w"], ref)
        # Tables cover the transition up to 3 P_sat of loading (or the top of a measured curve).
        domain = TableDomain(p_opt_w=(0.0, 3.0 * float(p.p_sat_w)))
        params = {p.detector_id: p}
        env = EnvironmentBlock(s["t_bath_k"], s["b_field_t"], s["v_thev_v"][None, :])
        samples[name] = {"p_opt_w": s["p_opt_w"], "region": reg}
        v_frac = s["v_thev_v"] / p.v_thev_v
        in_domain = (v_frac >= domain.v_frac[0]) & (v_frac <= domain.v_frac[1])
        stats[name] = {}
        for kind in kinds:
            if progress:
                progress(f"{name}/{kind}")
            opts = {}
            if kind == "table":
                opts["bank"] = build_bank(params, kind="table", domain=domain)
            elif kind == "grid":
                opts["bank"] = build_bank(params, kind="grid", domain=domain)
            elif kind in ("linear", "electrical"):
                opts["domain"] = domain
            conv = make_converter(kind, params, **opts)
            out = conv.convert([p.detector_id], s["counts_i"][None, :], s["counts_q"][None, :], env)
            unusable = (out.flags[0] & fl.UNUSABLE) != 0
            # Flagged: no value given, or a warning that the value is suspect (ENV_OUT_OF_RANGE
            # is information: the structured table stays exact there, so its values are checked;
            # NONLINEAR is the baselines' own: off the exact inverse by more than their tolerance).
            flagged = (out.flags[0] & (fl.UNUSABLE | fl.PHASE_RESIDUAL | fl.NONLINEAR)) != 0
            err = out.p_opt_w[0] - ref
            samples[name][kind] = {"error_w": err, "flagged": flagged}
            per = {}
            for ri, region in enumerate(REGIONS):
                m = reg == ri
                e = np.abs(err[m & ~flagged])
                per[region] = {
                    "n": int(m.sum()),
                    "flagged_frac": float(flagged[m].mean()) if m.any() else 0.0,
                    "n_in_domain": int((m & in_domain).sum()),
                    "flagged_frac_in_domain": float(flagged[m & in_domain].mean()) if (m & in_domain).any() else 0.0,
                    "unusable_frac": float(unusable[m].mean()) if m.any() else 0.0,
                    "by_flag": {nm: int(np.count_nonzero(out.flags[0][m] & bit)) for bit, nm in fl.NAMES.items()
                                if np.any(out.flags[0][m] & bit)},
                    "worst_unflagged_error_w": float(np.nanmax(e)) if e.size else 0.0,
                    "p_opt_range_w": [float(s["p_opt_w"][m].min()), float(s["p_opt_w"][m].max())] if m.any() else [],
                }
            stats[name][kind] = per
    return RangeResult(stats=stats, samples=samples)


# --- noise-aware trust (issue 26) ---------------------------------------------------------

# The readout: 2 counts rms on I and Q at 1e-12 A/count.
NOISE_SWEEP_READOUT_A = 2e-12
# Mid-transition band whose samples must stay unflagged (at most 0.1 %).
MID_TRANSITION = (0.2, 0.8)


def _noise_stats(p, s, out, unc, tol: float, reg, in_domain) -> dict:
    """Figures of one model and kind against the TRUE power (see :func:`noise_sweep`)."""
    f = unc.flags[0]
    suspect = fl.UNUSABLE | fl.PHASE_RESIDUAL | fl.NONLINEAR
    flagged_before = (out.flags[0] & suspect) != 0
    flagged = (f & (suspect | fl.LOW_RESPONSIVITY)) != 0
    p_true = s["p_opt_w"]
    err = np.abs(unc.p_opt_w[0] - p_true)
    sig = unc.sigma_p_w[0].astype(float)
    bound = np.maximum(1e-17, model.K_SIGMA * sig)
    ok = ~flagged
    with np.errstate(invalid="ignore", divide="ignore"):
        ratio = err / sig
    r_frac = s["r_ohm"] / float(p.r_normal_ohm)
    on = s["state"] == model.STATE_TRANSITION
    mid = on & in_domain & (r_frac >= MID_TRANSITION[0]) & (r_frac <= MID_TRANSITION[1])
    bad_before = ~flagged_before & ~(err <= 1e-17)
    return {
        "n": int(err.size),
        "unflagged": int(ok.sum()),
        "worst_unflagged_error_w": float(np.nanmax(err[ok])) if ok.any() else 0.0,
        "worst_unflagged_error_over_sigma_p": float(np.nanmax(ratio[ok])) if ok.any() else 0.0,
        "unflagged_beyond_bound": int(np.count_nonzero(ok & ~(err <= bound))),
        "max_unflagged_sigma_p_w": float(np.nanmax(sig[ok])) if ok.any() else 0.0,
        "tolerance_w": tol,
        "unflagged_sigma_p_within_tolerance": bool(np.all(sig[ok] <= tol)) if ok.any() else True,
        "transition_flagged_frac": float(flagged[reg == REGIONS.index("transition")].mean())
        if np.any(reg == REGIONS.index("transition")) else 0.0,
        "mid_transition_n": int(mid.sum()),
        "mid_transition_flagged_frac": float(flagged[mid].mean()) if mid.any() else 0.0,
        "low_responsivity": int(np.count_nonzero(f & fl.LOW_RESPONSIVITY)),
        "without_low_responsivity": {
            "unflagged_beyond_1e-17_w": int(bad_before.sum()),
            "worst_unflagged_error_w": float(np.nanmax(err[~flagged_before])) if (~flagged_before).any() else 0.0,
            "p_opt_range_w": ([float(p_true[bad_before].min()), float(p_true[bad_before].max())]
                              if bad_before.any() else []),
        },
    }


def noise_sweep(n_samples: int = 20_000, readout_noise_a: float = NOISE_SWEEP_READOUT_A,
                kinds=("table", "grid", "exact", "linear", "electrical"), seed: int = 0, settings=None,
                progress=None) -> dict:
    """The operating-range sweep with realistic readout noise, declared to the converter.

    Each transition model's detector (:func:`range_detectors`) through
    :func:`range_samples` with ``readout_noise_a`` per quadrature; every kind
    converts with the same noise declared (``readout_noise_a`` option) and
    :func:`core.uncertainty.sigma_p_block` adds sigma_P and LOW_RESPONSIVITY.
    Errors are against the TRUE optical power. Per model and kind:
    ``worst_unflagged_error_w``, ``unflagged_beyond_bound`` (unflagged
    samples further than ``max(1e-17 W, 7 sigma_P)``: must be 0),
    ``unflagged_sigma_p_within_tolerance``, ``transition_flagged_frac``,
    ``mid_transition_flagged_frac`` (true R in 0.2-0.8 R_n, bias in the
    table domain: at most 0.1 %), and ``without_low_responsivity``: the same
    samples judged by the other flags alone (the issue's measurement).

    Parameters
    ----------
    settings : core.uncertainty.UncertaintySettings, optional
        ``readout_noise_a`` is replaced by the sweep's.
    """
    import dataclasses

    from mntes_stream.core import uncertainty as unc_mod
    from mntes_stream.core.convert import EnvironmentBlock, make_converter
    from mntes_stream.core.tables import TableDomain, build_bank

    base = settings or unc_mod.UncertaintySettings()
    cfg = dataclasses.replace(base, readout_noise_a=float(readout_noise_a))
    out: dict = {"readout_noise_a": float(readout_noise_a), "samples_per_model": int(n_samples),
                 "settings": {k: getattr(cfg, k) for k in ("sigma_p_factor", "sigma_p_tolerance_w",
                                                           "low_responsivity_unusable")},
                 "models": {}}
    for k, (name, p) in enumerate(range_detectors().items()):
        s = range_samples(p, n_samples, seed + k, readout_noise_a=readout_noise_a)
        reg = _regions(p, s)
        domain = TableDomain(p_opt_w=(0.0, 3.0 * float(p.p_sat_w)))
        params = {p.detector_id: p}
        env = EnvironmentBlock(s["t_bath_k"], s["b_field_t"], s["v_thev_v"][None, :])
        v_frac = s["v_thev_v"] / p.v_thev_v
        in_domain = (v_frac >= domain.v_frac[0]) & (v_frac <= domain.v_frac[1])
        per_kind = out["models"][name] = {}
        for kind in kinds:
            if progress:
                progress(f"noise {name}/{kind}")
            opts: dict = {"readout_noise_a": float(readout_noise_a)}
            if kind in ("table", "grid"):
                opts["bank"] = build_bank(params, kind=kind, domain=domain)
            elif kind in ("linear", "electrical"):
                opts["domain"] = domain
            conv = make_converter(kind, params, **opts)
            ci, cq = s["counts_i"][None, :], s["counts_q"][None, :]
            blk = conv.convert([p.detector_id], ci, cq, env)
            nm = unc_mod.noise_model(conv.params, cfg)
            unc = unc_mod.sigma_p_block(conv, [p.detector_id], ci, cq, env, blk, nm)
            per_kind[kind] = _noise_stats(p, s, blk, unc, float(nm.tolerance_w[0]), reg, in_domain)
            per_kind[kind]["nominal_sigma_p_w"] = float(nm.nominal_sigma_p_w[0])
    return out

"""LOW_RESPONSIVITY in the conversion's own pass (issue 32, item 5): the flags the full sigma_P pass gives, to
the sample, on realistic and hostile blocks (the top of the transition, the rails, the tolerance itself); the
power untouched; on by default in the live converter and offline ``convert``."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from mntes_stream.core import flags as fl
from mntes_stream.core import model
from mntes_stream.core import uncertainty as U
from mntes_stream.core.convert import EnvironmentBlock, make_converter
from mntes_stream.core.sweep import range_detectors
from mntes_stream.core.tables import TableDomain, build_bank
from mntes_stream.errors import ConfigError

LOW = np.uint16(fl.LOW_RESPONSIVITY)


def _check_fused(conv, ids, ci, cq, env, noise):
    """The fused flags against the sigma_P pass on the same block; returns (fused block, sigma_P pass)."""
    plain = conv.convert(ids, ci, cq, env)
    ref = U.sigma_p_block(conv, ids, ci, cq, env, plain, noise)
    fused = U.low_responsivity_block(conv, ids, ci, cq, env, noise)
    assert np.array_equal(fused.flags, ref.flags)
    assert np.array_equal(fused.flags & ~LOW, plain.flags)
    assert np.array_equal(fused.p_opt_w, ref.p_opt_w, equal_nan=True)
    return fused, ref


def _transition_block(p, n=1500, bias=(0.95, 1.0, 1.05), fields=(-4e-5, 0.0, 6e-5)):
    """Noiseless counts of one detector from no load to 2.9 P_sat (across the top of the transition), at
    several biases and fields: rows (bias, field), the same detector."""
    rows_i, rows_q, vs, bs = [], [], [], []
    p_opt = np.linspace(0.0, 2.9 * p.p_sat_w, n)
    tb = np.full(n, 0.101)
    for fv in bias:
        for bf in fields:
            v, b = np.full(n, fv * p.v_thev_v), np.full(n, bf)
            op = model.solve_operating_point(p, p_opt, tb, b, v)
            c = model.readout_current_a(p, op.i_a, b) / p.gain_a_per_count
            rows_i.append(c.real)
            rows_q.append(c.imag)
            vs.append(v)
            bs.append(b)
    ci, cq = np.array(rows_i), np.array(rows_q)
    env = EnvironmentBlock(t_bath_k=np.broadcast_to(tb, ci.shape), b_field_t=np.array(bs), v_thev_v=np.array(vs))
    return [p.detector_id] * ci.shape[0], ci, cq, env


@pytest.mark.parametrize("name", list(range_detectors()))
def test_fused_flags_equal_the_sigma_p_pass_across_the_top_of_the_transition(name):
    p = range_detectors()[name]
    bank = build_bank({p.detector_id: p}, kind="table", domain=TableDomain(p_opt_w=(0.0, 3.0 * p.p_sat_w)))
    conv = make_converter("table", None, bank=bank)
    ids, ci, cq, env = _transition_block(p)
    noise = U.noise_model(conv.params)
    fused, ref = _check_fused(conv, ids, ci, cq, env, noise)
    low = (fused.flags & LOW) != 0
    # The top of the transition is flagged before SATURATED, the middle is not: the test sees both sides.
    assert 0.05 < low.mean() < 0.9
    usable = (fused.flags & fl.UNUSABLE) == 0
    assert np.any(usable & ~low) and np.any(usable & low)
    # Where sigma_P equals the tolerance to the last bit the screen cannot tell, and the exact sigma_P decides:
    # with a sample's own float64 sigma_P (the scalar reference) as the tolerance, that sample is not flagged
    # and one a hair below flags it, in both passes alike.
    from mntes_stream.core import _kernels

    a = bank.arrays
    q = tuple(float(x) for x in conv._row_constants()[0])
    lq = tuple(float(x) for x in noise.low_record(conv)[0])
    for row, col in list(zip(*np.nonzero(usable)))[:: max(1, int(usable.sum()) // 6)]:
        sp = _kernels._sigma_sample(float(ci[row, col]), float(cq[row, col]), float(env.b_field_t[row, col]),
                                    float(env.v_thev_v[row, col]), q, lq, a["r_knot_ohm"], a["cell_interval"],
                                    a["coeffs"])
        assert sp == pytest.approx(float(ref.sigma_p_w[row, col]), rel=1e-6)
        for tol, flagged in ((sp, False), (np.nextafter(sp, 0.0), True)):
            tight = dataclasses.replace(noise, tolerance_w=np.full(1, tol))
            fused_t, _ = _check_fused(conv, ids, ci, cq, env, tight)
            assert bool(fused_t.flags[row, col] & LOW) == flagged


def test_fused_flags_equal_on_a_realistic_and_a_hostile_block():
    from mntes_stream.bench.convert import synthetic_block, synthetic_params

    params = synthetic_params(24, seed=5)
    ids, ci, cq, env = synthetic_block(params, 1200, seed=6, bad_fraction=0.02)
    conv = make_converter("table", params)
    noise = U.noise_model(conv.params)
    fused, _ = _check_fused(conv, ids, ci, cq, env, noise)
    assert 0 < np.count_nonzero(fused.flags & LOW) < fused.flags.size
    # Hostile: counts anywhere (rails, zero, sign flips, huge), unknown rows, an environment off the domain.
    rng = np.random.default_rng(7)
    hi = rng.choice([0, 1, -1, 2**31 - 1, -(2**31), 40_000_000], size=ci.shape, p=[0.02, 0.01, 0.01, 0.02, 0.02, 0.92])
    ci_h = np.where(hi == 40_000_000, ci + rng.integers(-3_000_000, 3_000_000, ci.shape), hi).astype(np.int32)
    cq_h = np.where(rng.random(ci.shape) < 0.05, -cq, cq).astype(np.int32)
    ids_h = list(ids)
    ids_h[3] = "b9m9c999"
    v = np.array(env.v_thev_v, dtype=float)
    v[5] *= 1.4
    env_h = EnvironmentBlock(t_bath_k=env.t_bath_k * np.where(np.arange(ci.shape[1]) % 97 == 0, 3.0, 1.0),
                             b_field_t=env.b_field_t * 40, v_thev_v=v)
    fused_h, _ = _check_fused(conv, ids_h, ci_h, cq_h, env_h, noise)
    assert np.all(fused_h.flags[3] & fl.UNKNOWN_CHANNEL)
    # An absolute tolerance (the noise then matters) and a tolerance no sample reaches.
    for s in (U.UncertaintySettings(sigma_p_tolerance_w=2e-18), U.UncertaintySettings(sigma_p_factor=1e6)):
        _check_fused(conv, ids, ci, cq, env, U.noise_model(conv.params, s))



def test_the_screen_decides_only_where_its_w_prime_is_near_the_references():
    """The kernel's W' (synthetic division) is trusted only where W''s terms stay within 1e4 of |W'| on every
    interval (``_kernels.w1_screenable``); a detector that fails it has every sample decided by the exact
    sigma_P, with the same flags."""
    from mntes_stream.bench.convert import synthetic_block, synthetic_params
    from mntes_stream.core import _kernels

    # Three detectors of two unit intervals each: W' = 1 (fine); 1 - 2u, through zero on the first interval;
    # 1e-5 + 2u, its terms 2e5 times its smallest value.
    ko = np.array([0, 3, 6, 9])
    x = np.tile([0.0, 1.0, 2.0], 3)
    coef = np.zeros((9, 8))
    coef[0:3, 1] = 1.0
    coef[3:6, 1], coef[3, 2] = 1.0, -1.0
    coef[6:9, 1], coef[6, 2] = 1e-5, 1.0
    assert _kernels.w1_screenable(ko, x, coef).tolist() == [True, False, False]
    assert _kernels.w1_screenable(ko, x, coef * -3.0).tolist() == [True, False, False]  # the sign does not matter

    params = synthetic_params(24, seed=5)
    ids, ci, cq, env = synthetic_block(params, 1200, seed=6, bad_fraction=0.02)
    conv = make_converter("table", params)
    noise = U.noise_model(conv.params)
    rec = noise.low_record(conv)
    assert np.all(rec[:, -1] == 1.0)  # the bench's detectors: all screenable
    ref = U.sigma_p_block(conv, ids, ci, cq, env, conv.convert(ids, ci, cq, env), noise)
    exact = np.array(rec)
    exact[::2, -1] = 0.0  # every other detector by the exact sigma_P alone
    out = conv.convert(ids, ci, cq, env, low_responsivity=exact)
    assert np.array_equal(out.flags, ref.flags)
    assert 0 < np.count_nonzero(out.flags[::2] & LOW) < out.flags[::2].size

def test_unusable_setting_drops_the_value_and_a_foreign_record_is_refused():
    from mntes_stream.bench.convert import synthetic_block, synthetic_params

    params = synthetic_params(8, seed=2)
    ids, ci, cq, env = synthetic_block(params, 400, seed=3)
    conv = make_converter("table", params)
    noise = U.noise_model(conv.params, U.UncertaintySettings(low_responsivity_unusable=True))
    out = U.low_responsivity_block(conv, ids, ci, cq, env, noise)
    low = (out.flags & LOW) != 0
    assert low.any() and np.all(np.isnan(out.p_opt_w[low]))
    plain = conv.convert(ids, ci, cq, env)
    assert np.array_equal(out.p_opt_w[~low], plain.p_opt_w[~low], equal_nan=True)
    with pytest.raises(ConfigError, match="shape"):
        conv.convert(ids, ci, cq, env, low_responsivity=np.zeros((3, 10)))
    numpy_conv = make_converter("table", params, backend="numpy")
    with pytest.raises(ConfigError, match="does not flag"):
        numpy_conv.convert(ids, ci, cq, env, low_responsivity=noise.low_record(conv))
    # The numpy backend gets the same flags by the sigma_P pass.
    assert np.array_equal(U.low_responsivity_block(numpy_conv, ids, ci, cq, env, noise).flags & LOW, out.flags & LOW)


def test_with_noise_is_noise_model_with_that_noise():
    params = range_detectors()
    plist = list(params.values())
    s = U.UncertaintySettings(sigma_p_tolerance_w=1e-18)
    base = U.noise_model(plist, s)
    noise = np.array([3e-12, 5e-11, 0.0])
    direct = U.noise_model(plist, s, measured_a={p.detector_id: float(x) for p, x in zip(plist, noise)})
    moved = base.with_noise(noise, direct.source, "live")
    assert np.array_equal(moved.sigma_i_a, direct.sigma_i_a)
    assert np.array_equal(moved.nominal_sigma_p_w, direct.nominal_sigma_p_w)
    assert np.array_equal(moved.tolerance_w, direct.tolerance_w)
    assert moved.provenance()["readout_noise_measured_from"] == "live"
    with pytest.raises(ConfigError):
        base.with_noise([1.0, np.nan, 0.0], direct.source)


def test_noise_window_measures_white_noise_of_known_level_live():
    """Chunks of 20 samples with offsets, a drift, a slow HWP-like line, glitches and rails on top of white noise
    of known level: every channel's live estimate within 6 % of it (its statistical spread at 4096 differences
    is ~1.5 %), and near the offline estimator's on the same counts (6 %)."""
    rng = np.random.default_rng(11)
    n_det, n_samp, chunk = 6, 24_000, 20
    level = np.array([1.5, 3.0, 5.0, 8.0, 20.0, 60.0])  # counts rms
    t = np.arange(n_samp)
    slow = 4000.0 * np.sin(2 * np.pi * 4 * t / 152.6 / 10)[None, :] + 0.05 * t[None, :] + rng.uniform(-1e6, 1e6, (n_det, 1))
    ci = np.rint(slow + rng.normal(0, 1, (n_det, n_samp)) * level[:, None])
    cq = np.rint(0.3 * slow + rng.normal(0, 1, (n_det, n_samp)) * level[:, None])
    glitch = rng.random(ci.shape) < 1e-3
    ci[glitch] += 50_000
    cq[rng.random(ci.shape) < 1e-3] = 2**31 - 1
    win = U.NoiseWindow(n_det + 1, window=4096)
    rows = np.array([0, 1, 2, 3, 4, 5])
    renewed = []
    for a in range(0, n_samp, chunk):
        renewed.append(win.add(rows, ci[:, a:a + chunk], cq[:, a:a + chunk]))
    assert np.isnan(win.sigma_counts[6])  # a detector never seen has no estimate
    assert sum(r.size for r in renewed) >= 6 * 2  # every channel renewed more than once
    np.testing.assert_allclose(win.sigma_counts[:6], level, rtol=0.06)
    offline, _ = U.white_noise_counts(np.where(np.abs(cq) < 2**31 - 1, cq, np.nan)[:, -8192:])
    np.testing.assert_allclose(win.sigma_counts[:6], offline, rtol=0.06)
    with pytest.raises(ConfigError):
        U.NoiseWindow(3, window=10)


def test_live_pipeline_measures_the_noise_and_the_provenance_says_so():
    """``[uncertainty] readout_noise = "measured"``: the simulator's counts carry no readout noise (rounding only;
    a dark, steady run: a bright HWP line's curvature would count as noise), so once each channel's window is
    complete its noise is measured far below the configured 2.76e-11 A, sigma_P falls with it, and the
    provenance names the live measurement."""
    from mntes_stream.io.messages import PowerChunk, Provenance
    from mntes_stream.pipeline import ConverterPipeline, PipelineConfig
    from mntes_stream.service.source import MinimalSource, SourceConfig

    src = MinimalSource(SourceConfig(modules=1, channels=4, hwp_2f_amplitude_w=0.0, t_bath_swing_k=0.0,
                                     b_field_swing_t=0.0))
    msgs = list(src.batches(1_700_000_000_000_000_000, 3.0))
    conv = make_converter("table", {p.detector_id: p for p in src.params})

    def run(settings):
        pipe = ConverterPipeline(conv, PipelineConfig(setup="lab"), clock=None, uncertainty=settings, sigma_p=True)
        provs, power = [Provenance.from_bytes(pipe.provenance_bytes())], []
        for t, batch in msgs:
            power += [PowerChunk.from_bytes(p) for k, p in pipe.handle_many([(k, p, t) for k, p in batch])
                      if "/power/" in k]
            provs.append(Provenance.from_bytes(pipe.provenance_bytes()))
        return power, provs

    configured, prov_c = run(U.UncertaintySettings())
    measured, prov_m = run(U.UncertaintySettings(readout_noise="measured", noise_window_samples=256))
    assert prov_c[-1].noise["readout_noise_sources"] == {"default": 4}
    assert prov_m[0].noise["readout_noise_sources"] == {"default": 4}  # before a window is complete
    last = prov_m[-1].noise
    assert last["readout_noise_sources"] == {"measured:live": 4} and last["readout_noise_measured_from"].startswith("live")
    assert last["readout_noise_a_range"][1] < 0.2 * 2.76e-11
    a, b = configured[-1], measured[-1]
    usable = (a.flags & fl.UNUSABLE) == 0
    assert usable.any() and np.all(b.sigma_p_w[usable] < 0.5 * a.sigma_p_w[usable])
    assert np.array_equal(a.p_opt_w, b.p_opt_w, equal_nan=True)


def test_nominal_gradients_are_solved_once_and_travel_with_a_restart_snapshot():
    import pickle

    import mntes_stream.pipeline.snapshot  # noqa: F401 - registers how the converter's read-only views pickle

    params = {p.detector_id: p for p in range_detectors().values()}
    conv = make_converter("table", params)
    grad = U.nominal_gradients(conv)
    assert U.nominal_gradients(conv) is grad  # kept on the converter
    restored = pickle.loads(pickle.dumps(conv))  # what pipeline/snapshot.py stores
    assert np.array_equal(U.nominal_gradients(restored), grad)
    s = U.UncertaintySettings()
    a, b = U.noise_model(conv.params, s), U.noise_model(conv.params, s, gradients=grad)
    assert np.array_equal(a.tolerance_w, b.tolerance_w) and np.array_equal(a.nominal_sigma_p_w, b.nominal_sigma_p_w)
    with pytest.raises(ConfigError):
        U.noise_model(conv.params, s, gradients=grad[:1])


def test_auto_flags_only_where_the_kernel_does_it_in_its_own_pass():
    """``low_responsivity = "auto"`` (only_fused): a converter that would need the sigma_P pass (here the numpy
    backend) flags nothing and names no noise; ``"on"``: it flags as the compiled kernel does."""
    from mntes_stream.io.messages import PowerChunk, Provenance
    from mntes_stream.pipeline import ConverterPipeline, PipelineConfig
    from mntes_stream.service.source import MinimalSource, SourceConfig

    src = MinimalSource(SourceConfig(modules=1, channels=4, hwp_2f_amplitude_w=2e-13))
    msgs = list(src.batches(1_700_000_000_000_000_000, 1.0))
    params = {p.detector_id: p for p in src.params}
    s = U.UncertaintySettings(sigma_p_factor=1.01)

    def run(conv, only_fused):
        pipe = ConverterPipeline(conv, PipelineConfig(setup="lab"), clock=None, uncertainty=s, only_fused=only_fused)
        out = [PowerChunk.from_bytes(p) for t, b in msgs for k, p in pipe.handle_many([(k, p, t) for k, p in b])
               if "/power/" in k]
        return out, Provenance.from_bytes(pipe.provenance_bytes()).noise

    compiled, numpy_conv = make_converter("table", params), make_converter("table", params, backend="numpy")
    fused, noise_fused = run(compiled, True)
    skipped, noise_skipped = run(numpy_conv, True)
    full, _ = run(numpy_conv, False)
    assert noise_skipped == {} and noise_fused["sigma_p_published"] is False
    assert sum(int(np.count_nonzero(c.flags & LOW)) for c in fused) > 0
    for a, b, c in zip(fused, skipped, full):
        assert not np.any(b.flags & LOW) and np.array_equal(a.flags & LOW, c.flags & LOW)

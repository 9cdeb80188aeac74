"""sigma_P (issue 26): the compiled table route, the model route, finite differences and brentq agree;
LOW_RESPONSIVITY makes every unflagged sample as good as its noise allows."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.optimize import brentq

from mntes_stream.core import flags as fl
from mntes_stream.core import model
from mntes_stream.core import uncertainty as U
from mntes_stream.core.convert import EnvironmentBlock, make_converter
from mntes_stream.core.sweep import range_detectors
from mntes_stream.core.tables import TableDomain, build_bank
from mntes_stream.errors import ConfigError

DETECTORS = range_detectors()
NOISE_A = 2e-12  # the 2 counts rms at 1e-12 A/count


def _setup(name: str, n: int = 600, b_field_t: float = 4e-5):
    """A converter and noiseless counts of one detector from 0 to 2.9 P_sat (noise-free: exact truth)."""
    p = DETECTORS[name]
    bank = build_bank({p.detector_id: p}, kind="table", domain=TableDomain(p_opt_w=(0.0, 3.0 * p.p_sat_w)))
    conv = make_converter("table", None, bank=bank, readout_noise_a=NOISE_A)
    p_opt = np.linspace(0.0, 2.9 * p.p_sat_w, n)
    tb, b, v = np.full(n, 0.101), np.full(n, b_field_t), np.full(n, 1.02 * p.v_thev_v)
    op = model.solve_operating_point(p, p_opt, tb, b, v)
    i = model.readout_current_a(p, op.i_a, b)
    c = i / p.gain_a_per_count
    env = EnvironmentBlock(tb, b, v[None, :])
    return p, conv, c.real[None, :], c.imag[None, :], env, i, (tb, b, v)


@pytest.mark.parametrize("name", list(DETECTORS))
def test_sigma_p_kernel_model_finite_differences_and_brentq(name):
    p, conv, ci, cq, env, i, (tb, b, v) = _setup(name)
    nm = U.noise_model(conv.params, U.UncertaintySettings(readout_noise_a=NOISE_A))
    blk = conv.convert([p.detector_id], ci, cq, env)
    k = U.sigma_p_block(conv, [p.detector_id], ci, cq, env, blk, nm)
    m = U.sigma_p_block(conv, [p.detector_id], ci, cq, env, blk, nm, backend="numpy")
    usable = (blk.flags[0] & fl.UNUSABLE) == 0
    assert usable.sum() > 150
    sk, sm = k.sigma_p_w[0].astype(float), m.sigma_p_w[0].astype(float)
    assert np.isfinite(sk[usable]).all() and np.isnan(sk[~usable]).all()
    # Compiled table route against the model route: the table's own accuracy (1e-20 W) and float32.
    np.testing.assert_allclose(sk[usable], sm[usable], rtol=2e-5)
    assert np.array_equal(k.flags, m.flags)
    sigma_i = float(nm.sigma_i_a[0])
    assert sigma_i == pytest.approx(np.hypot(NOISE_A, abs(p.gain_a_per_count) / np.sqrt(12)))

    # Finite differences of the exact inverse in I and Q (independent of the analytic gradient).
    def inv(x):
        return model.invert_current(p, x, tb, b, v).p_opt_w

    h = 1e-7 * np.abs(i)
    grad = [(inv(i + d) - inv(i - d)) / (2 * h) for d in (h, 1j * h)]
    fd = sigma_i * np.hypot(*grad)
    # One-sided differences agree where the inverse is smooth (not across a PCHIP knot of a measured curve).
    right = [(inv(i + d) - inv(i)) / h for d in (h, 1j * h)]
    smooth = usable & (np.abs(sigma_i * np.hypot(*right) / fd - 1) < 1e-4)
    assert smooth.sum() > 0.9 * usable.sum()
    np.testing.assert_allclose(sm[smooth], fd[smooth], rtol=1e-4)

    # brentq: the forward response, dI/dP by central differences of solved states; sigma_i / |dI/dP|.
    idx = np.flatnonzero(usable)[:: max(1, usable.sum() // 25)]
    lo, hi = (float(x) for x in model.branch_bounds_ohm(p))
    ratio = []
    for j in idx:
        def current(pw):
            r = brentq(lambda r: float(model.power_of_resistance_w(p, r, tb[j], b[j], v[j])) - pw, lo, hi,
                       xtol=1e-16, rtol=1e-15)
            return complex(model.tes_current_a(p, r, v[j]))
        dp = 1e-16
        pj = float(model.invert_current(p, i[j], tb[j], b[j], v[j]).p_opt_w)
        didp = (current(pj + dp) - current(pj - dp)) / (2 * dp)
        ratio.append(sm[j] / (sigma_i / abs(didp)))
    ratio = np.array(ratio)
    if p.current_shift_k_per_a == 0:
        np.testing.assert_allclose(ratio, 1.0, rtol=2e-4)
    else:
        # The inverse also reads |i|: its gradient is never smaller than the response curve's
        # (and, the current shift being small against the transition's slope, hardly larger).
        assert np.all(ratio >= 1 - 2e-4) and np.all(ratio < 1.05), ratio


def test_kernel_beyond_the_series_equals_the_model():
    """A 1 mT field shifts T_c by 12 mK: |delta / T_s| > 0.05, the kernel's lanes hand every sample to
    its scalar reference (the exact power), which must still equal the model route."""
    p, conv, ci, cq, env, *_ = _setup("arctan", n=300, b_field_t=1e-3)
    nm = U.noise_model(conv.params, U.UncertaintySettings(readout_noise_a=NOISE_A))
    blk = conv.convert([p.detector_id], ci, cq, env)
    k = U.sigma_p_block(conv, [p.detector_id], ci, cq, env, blk, nm)
    m = U.sigma_p_block(conv, [p.detector_id], ci, cq, env, blk, nm, backend="numpy")
    usable = (blk.flags[0] & fl.UNUSABLE) == 0
    assert usable.sum() > 50
    np.testing.assert_allclose(k.sigma_p_w[0][usable], m.sigma_p_w[0][usable], rtol=2e-5)
    assert np.array_equal(k.flags, m.flags)


def test_low_responsivity_where_sigma_exceeds_the_tolerance_and_the_options():
    p, conv, ci, cq, env, i, _ = _setup("arctan")
    blk = conv.convert([p.detector_id], ci, cq, env)
    base = U.UncertaintySettings(readout_noise_a=NOISE_A)
    nm = U.noise_model(conv.params, base)
    out = U.sigma_p_block(conv, [p.detector_id], ci, cq, env, blk, nm)
    s = out.sigma_p_w[0]
    low = (out.flags[0] & fl.LOW_RESPONSIVITY) != 0
    assert nm.tolerance_w[0] == pytest.approx(3.0 * nm.nominal_sigma_p_w[0])
    with np.errstate(invalid="ignore"):
        assert np.array_equal(low, s > nm.tolerance_w[0])
    assert 10 < low.sum() < np.isfinite(s).sum()
    assert np.isfinite(out.p_opt_w[0][low]).all()  # a warning by default: the value is kept
    assert np.array_equal(out.flags & ~np.uint16(fl.LOW_RESPONSIVITY), blk.flags)
    # Absolute tolerance instead of the factor, and the unusable semantics.
    tight = dataclasses.replace(base, sigma_p_tolerance_w=2e-18, low_responsivity_unusable=True)
    nm2 = U.noise_model(conv.params, tight)
    out2 = U.sigma_p_block(conv, [p.detector_id], ci, cq, env, blk, nm2)
    low2 = (out2.flags[0] & fl.LOW_RESPONSIVITY) != 0
    assert low2.sum() > low.sum() and np.isnan(out2.p_opt_w[0][low2]).all()
    assert np.isnan(out2.sigma_p_w[0][low2]).all()
    assert nm2.provenance()["low_responsivity"] == "sigma_P > 2e-18 W"


def test_readout_noise_setting_measured_per_detector_and_module_and_provenance():
    ps = [DETECTORS["arctan"].replace(detector_id=d) for d in ("b0m0c000", "b0m0c001", "b0m1c000", "pixel")]
    nm = U.noise_model(ps, U.UncertaintySettings(), measured_a={"b0m0c001": 3e-12, "b0m0": 5e-12},
                       measured_from="dark.json")
    assert nm.source == ("measured:module", "measured:detector", "default", "default")
    np.testing.assert_allclose(nm.readout_noise_a, [5e-12, 3e-12, model.DEFAULT_READOUT_NOISE_A,
                                                    model.DEFAULT_READOUT_NOISE_A])
    prov = nm.provenance()
    assert prov["readout_noise_sources"] == {"default": 2, "measured:detector": 1, "measured:module": 1}
    assert prov["readout_noise_measured_from"] == "dark.json"
    # A larger noise gives a proportionally larger nominal sigma_P (quantisation is small here).
    assert nm.nominal_sigma_p_w[2] > 5 * nm.nominal_sigma_p_w[1]
    assert U.noise_model(ps[:1], U.UncertaintySettings(readout_noise_a=1e-12)).source == ("setting",)
    with pytest.raises(ConfigError, match="readout_noise_a"):
        U.UncertaintySettings(readout_noise_a=-1.0)
    with pytest.raises(ConfigError, match="sigma_p_factor"):
        U.UncertaintySettings(sigma_p_factor=0.5)
    with pytest.raises(ConfigError, match="finite number"):
        U.noise_model(ps, measured_a={"b0m0": float("nan")})


def test_noise_model_of_other_detectors_is_refused():
    p, conv, ci, cq, env, *_ = _setup("arctan", n=20)
    blk = conv.convert([p.detector_id], ci, cq, env)
    other = U.noise_model([p.replace(detector_id="x")])
    with pytest.raises(ConfigError, match="other detectors"):
        U.sigma_p_block(conv, [p.detector_id], ci, cq, env, blk, other)


def test_noise_sweep_meets_the_acceptance():
    """validate --range's noise figures in small: the issue's readout noise, declared."""
    from mntes_stream.core.sweep import noise_sweep

    res = noise_sweep(n_samples=3000, kinds=("table", "exact"), seed=5)
    for name, kinds in res["models"].items():
        for kind, d in kinds.items():
            where = (name, kind)
            assert d["unflagged"] > 300, where
            assert d["unflagged_beyond_bound"] == 0, where
            assert d["unflagged_sigma_p_within_tolerance"], where
            assert d["mid_transition_n"] > 250 and d["mid_transition_flagged_frac"] <= 1e-3, where
            assert d["worst_unflagged_error_w"] <= max(1e-17, 7 * d["max_unflagged_sigma_p_w"]), where
            # What the issue measured: without the new flag, unflagged samples far off the truth.
            assert d["without_low_responsivity"]["unflagged_beyond_1e-17_w"] > 50, where


def test_power_message_carries_sigma_p_optionally():
    """The optional mntes.power field: absent when not computed, float32 of the power's shape, schema-valid."""
    import schema_check

    from mntes_stream.errors import SchemaError
    from mntes_stream.io import messages as m

    p = np.array([[1e-13, np.nan, 3e-13]])
    f = np.array([[0, fl.SATURATED, fl.LOW_RESPONSIVITY]], dtype=np.uint16)
    args = ("lab", 0, 1, [2], ["b0m1c002"], 7, 10**18, 152.5, p, f, "id", "table", 10**18, 10**18 + 5)
    plain = m.PowerChunk(*args)
    assert b"sigma_p_w" not in plain.to_bytes()
    sig = np.array([[1e-18, np.nan, 9e-18]], dtype=np.float32)
    msg = m.PowerChunk(*args, sigma_p_w=sig)
    payload = msg.to_bytes()
    schema_check.validate_payload(payload)
    back = m.decode(payload)
    np.testing.assert_array_equal(back.sigma_p_w, sig)
    assert back.sigma_p_w.dtype == np.float32
    # 4 bytes a sample beside the power's 10 (float64 and uint16 flags).
    assert len(payload) - len(plain.to_bytes()) == pytest.approx(len("sigma_p_w") + 4 * sig.size + 30, abs=20)
    values = {k: getattr(plain, k) for k in ("setup", "board", "module", "channels", "detector_ids", "seq", "t0_ns",
                                             "sample_rate_hz", "p_opt_w", "flags", "table_identity",
                                             "converter_kind", "source_t_pub_ns", "t_pub_ns", "t_ns", "late")}
    assert m.PowerChunk.unchecked(**values).to_bytes() == plain.to_bytes()  # callers from before the field
    with pytest.raises(SchemaError, match="shape of p_opt_w"):
        m.PowerChunk(*args, sigma_p_w=np.zeros((1, 2), np.float32))
    with pytest.raises(SchemaError, match=">= 0"):
        m.PowerChunk(*args, sigma_p_w=-sig)


def test_sigma_p_is_carried_to_the_feeds_hdf5_and_frameworks(tmp_path):
    """Power chunks with and without sigma_P, a missing chunk, a chunk with its rows reordered and one
    missing: the feeds put sigma_P where it was given and NaN elsewhere, bit for bit, and the HDF5 export,
    sotodlib's AxisManager and TOAST's observation carry it."""
    from mntes_stream.core.ids import detector_id
    from mntes_stream.feeds import RecordedPower, export_hdf5, read_hdf5
    from mntes_stream.io import keys
    from mntes_stream.io.mcap import McapFileWriter
    from mntes_stream.io.messages import PowerChunk

    t0, rate, n = 1_700_000_000_000_000_000, 100.0, 10
    step = int(n * 1e9 / rate)
    rng = np.random.default_rng(2)
    sent = {}
    with McapFileWriter(tmp_path / "p.mcap") as w:
        for seq in range(12):
            if seq == 4:
                continue  # a gap
            ch = np.array([2, 0, 1] if seq == 7 else [0, 1, 2, 3], dtype=np.int32)
            p = rng.normal(1e-12, 1e-14, (ch.size, n))
            sig = rng.uniform(1e-18, 3e-18, (ch.size, n)).astype(np.float32) if seq < 9 else None
            c = PowerChunk(setup="t", board=0, module=0, channels=ch, detector_ids=[detector_id(0, 0, x) for x in ch],
                           seq=seq, t0_ns=t0 + seq * step, sample_rate_hz=rate, p_opt_w=p,
                           flags=np.zeros(p.shape, np.uint16), table_identity="tab", converter_kind="table",
                           source_t_pub_ns=t0, t_pub_ns=t0, sigma_p_w=sig)
            sent[seq] = c
            w.write(keys.power_key("t", 0, 0), c.to_bytes(), t0 + (seq + 1) * step)
    b = RecordedPower(tmp_path / "p.mcap").read()["t_b0m0"]
    assert b.sigma_p_w is not None and b.sigma_p_w.dtype == np.float32 and b.sigma_p_w.shape == b.p_opt_w.shape
    for seq in range(12):
        cols = slice(seq * n, (seq + 1) * n)
        if seq not in sent or sent[seq].sigma_p_w is None:
            assert np.isnan(b.sigma_p_w[:, cols]).all(), seq
            continue
        c = sent[seq]
        rows = [b.detectors.index(d) for d in c.detector_ids]
        np.testing.assert_array_equal(b.sigma_p_w[rows, cols], c.sigma_p_w)
        absent = [r for r in range(b.n_detectors) if r not in rows]
        assert np.isnan(b.sigma_p_w[absent, cols]).all()
    assert b.select(["b0m0c003"]).sigma_p_w.shape == (1, b.n_samples)
    export_hdf5(tmp_path / "p.mcap", tmp_path / "p.h5", block_samples=32)
    back = read_hdf5(tmp_path / "p.h5", "t_b0m0")
    np.testing.assert_array_equal(back.sigma_p_w, b.sigma_p_w)
    import h5py

    with h5py.File(tmp_path / "p.h5") as f:
        assert f["t_b0m0/sigma_p_w"].attrs["units"] == "W"
    from mntes_stream.feeds.frameworks import _common

    seg = _common.single_segment(b)
    pytest.importorskip("sotodlib.core", reason="sotodlib extra not installed")
    from mntes_stream.feeds.frameworks.sotodlib_io import to_axismanager

    am = to_axismanager(seg, sample_rate_hz=rate)
    np.testing.assert_array_equal(am.sigma_p_w, b.sigma_p_w)
    pytest.importorskip("toast", reason="toast extra not installed")
    from mntes_stream.feeds.frameworks.toast_io import to_toast

    obs = to_toast(seg, sample_rate_hz=rate)
    np.testing.assert_array_equal(obs.detdata["sigma_p_w"][:], b.sigma_p_w.astype(np.float64))
    pytest.importorskip("litebird_sim", reason="litebird extra not installed")
    from mntes_stream.feeds.frameworks.litebird_io import export_litebird, read_litebird

    export_litebird(tmp_path / "p.mcap", tmp_path / "lbs")
    (lobs,) = read_litebird(tmp_path / "lbs")
    np.testing.assert_array_equal(lobs.mntes_sigma_p_w, b.sigma_p_w)

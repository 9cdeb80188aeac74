"""Counts-to-power conversion: every kind against the exact inverse, every flag, bad input.

The exact inverse (``core.model.invert_current``) is the oracle; the forward
solve (``core.model.solve_operating_point``) makes the counts. Both backends
of the table kernel (numba and numpy) are checked.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mntes_stream.bench.convert import synthetic_params, tabulated_params
from mntes_stream.core import flags as fl
from mntes_stream.core import model
from mntes_stream.core.convert import (
    Converter,
    EnvironmentBlock,
    PowerBlock,
    make_converter,
    numba_available,
)
from mntes_stream.core.params import table1_params
from mntes_stream.core.tables import TableDomain, build_bank
from mntes_stream.core.transition import TabulatedTransition
from mntes_stream.errors import ConfigError, SchemaError

SPEC_P_W = (0.05e-12, 1.0e-12)
SPEC_T_BATH_K = (0.095, 0.105)
SPEC_B_T = (-100e-6, 100e-6)
SPEC_V_FRAC = (0.95, 1.05)
TARGET_W = 1e-19
BACKENDS = ("numba", "numpy")


@pytest.fixture(scope="module")
def params():
    out = synthetic_params(4, seed=11)
    out["b0m0c099"] = table1_params("b0m0c099")  # plain Table 1: no field, no current dependence
    tab = tabulated_params()
    out[tab.detector_id] = tab
    return out


@pytest.fixture(scope="module")
def bank(params):
    return build_bank(params, kind="table")


@pytest.fixture(scope="module")
def grid_bank(params):
    return build_bank(params, kind="grid", bias_frac=(0.95, 1.0, 1.05))


def forward_counts(p, p_opt_w, t_bath_k, b_field_t, v_thev_v, rounded=True):
    """Counts the readout would report for the given loading and environment (arrays broadcast)."""
    op = model.solve_operating_point(p, p_opt_w, t_bath_k, b_field_t, v_thev_v)
    assert np.all(op.state == model.STATE_TRANSITION)
    c = model.readout_current_a(p, op.i_a, b_field_t) / p.gain_a_per_count
    if rounded:
        return np.rint(c.real).astype(np.int32), np.rint(c.imag).astype(np.int32)
    return c.real.copy(), c.imag.copy()


def spec_grid():
    """Environment points including every edge of the specification and off-grid interior points."""
    p = np.array([0.05, 0.1377, 0.5, 0.8123, 1.0]) * 1e-12
    tb = np.array([0.095, 0.09871, 0.1, 0.10333, 0.105])
    b = np.array([-100e-6, -31.7e-6, 0.0, 47.3e-6, 100e-6])
    vf = np.array([0.95, 0.9871, 1.0, 1.0213, 1.05])
    grids = np.meshgrid(p, tb, b, vf, indexing="ij")
    return [g.ravel() for g in grids]


def convert_points(conv, params, p_w, tb, b, vf, rounded=True):
    """Convert one sample per point for every detector: per-detector env rows (n_det, n_pts)."""
    ids = list(params)
    ci, cq, v = [], [], []
    for q in params.values():
        i, qq = forward_counts(q, p_w, tb, b, vf * q.v_thev_v, rounded)
        ci.append(i)
        cq.append(qq)
        v.append(vf * q.v_thev_v)
    shape = (len(ids), np.size(p_w))
    env = EnvironmentBlock(np.broadcast_to(tb, shape), np.broadcast_to(b, shape), np.array(v))
    return conv.convert(ids, np.array(ci), np.array(cq), env)


@pytest.mark.parametrize("backend", BACKENDS)
def test_table_meets_1e19_w_over_the_spec_domain_and_its_edges(params, bank, backend):
    pts = spec_grid()
    exact = convert_points(make_converter("exact", params), params, *pts)
    table = convert_points(make_converter("table", params, bank=bank, backend=backend), params, *pts)
    assert_only_expected_saturation(params, pts, exact.flags)
    np.testing.assert_array_equal(table.flags, exact.flags)
    err = np.abs(table.p_opt_w - exact.p_opt_w)[exact.flags == 0]
    assert err.max() <= TARGET_W, err.max()


def assert_only_expected_saturation(params, pts, flags):
    """The spec domain is flag-free except at the top of the transition.

    There the counts' rounding moves the power by more than
    ``model.P_RESOLUTION_W`` (or the loop gain collapses): exactly the samples
    whose true R is at or above ``flag_thresholds().at_bias(V)[2]`` carry
    SATURATED, all at 0.8 pW or more; nothing else is flagged.
    """
    p_w, tb, b, vf = pts
    for k, p in enumerate(params.values()):
        r = model.solve_operating_point(p, p_w, tb, b, vf * p.v_thev_v).r_ohm
        saturated = r >= model.flag_thresholds(p).at_bias(vf * p.v_thev_v)[2]
        np.testing.assert_array_equal(flags[k], np.where(saturated, fl.SATURATED, 0))
        assert np.all(p_w[saturated] >= 0.8e-12)


def test_a_domain_equal_to_the_spec_covers_its_own_edges(params):
    tight = TableDomain(p_opt_w=SPEC_P_W, t_bath_k=SPEC_T_BATH_K, b_field_t=SPEC_B_T, v_frac=SPEC_V_FRAC)
    bank = build_bank(params, domain=tight)
    pts = spec_grid()
    exact = convert_points(make_converter("exact", params), params, *pts, rounded=False)
    table = convert_points(make_converter("table", None, bank=bank), params, *pts, rounded=False)
    assert_only_expected_saturation(params, pts, table.flags)
    ok = table.flags == 0
    assert np.abs(table.p_opt_w - exact.p_opt_w)[ok].max() <= TARGET_W


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    p_w=st.floats(*SPEC_P_W),
    tb=st.floats(*SPEC_T_BATH_K),
    b=st.floats(*SPEC_B_T),
    vf=st.floats(*SPEC_V_FRAC),
)
def test_table_matches_exact_at_arbitrary_environment_points(params, bank, p_w, tb, b, vf):
    arr = lambda x: np.array([x])  # noqa: E731
    exact = convert_points(make_converter("exact", params), params, arr(p_w), arr(tb), arr(b), arr(vf))
    table = convert_points(make_converter("table", params, bank=bank), params, arr(p_w), arr(tb), arr(b), arr(vf))
    assert np.array_equal(table.flags, exact.flags)
    ok = exact.flags == 0
    assert np.abs(table.p_opt_w - exact.p_opt_w)[ok].max(initial=0.0) <= TARGET_W


def test_tabulated_transition_is_reproduced_and_exact_inverse_recovers_truth(params, bank):
    tab = {k: v for k, v in params.items() if isinstance(v.transition, TabulatedTransition)}
    pts = spec_grid()
    # Unrounded counts: the exact inverse must give back the injected power itself.
    exact = convert_points(make_converter("exact", tab), tab, *pts, rounded=False)
    table = convert_points(make_converter("table", params, bank=bank), tab, *pts, rounded=False)
    ok = exact.flags == 0
    # The sharp-topped detector saturates at the high-power corner of the grid.
    assert ok.mean() > 0.7 and np.array_equal(table.flags, exact.flags)
    assert np.abs(exact.p_opt_w - pts[0])[ok].max() < 1e-21
    assert np.abs(table.p_opt_w - exact.p_opt_w)[ok].max() <= TARGET_W


def test_grid_route_meets_its_documented_accuracy(params, grid_bank):
    """The paper's route: bias on a tabulated state, B and bath anywhere in the spec."""
    p_w, tb, b, vf = spec_grid()
    on_state = np.isin(vf, (0.95, 1.0, 1.05))
    pts = [a[on_state] for a in (p_w, tb, b, vf)]
    exact = convert_points(make_converter("exact", params), params, *pts)
    for backend in BACKENDS:
        grid = convert_points(make_converter("grid", None, bank=grid_bank, backend=backend), params, *pts)
        assert np.array_equal(grid.flags, exact.flags)
        ok = exact.flags == 0
        assert np.abs(grid.p_opt_w - exact.p_opt_w)[ok].max() <= 5e-19  # README: grid accuracy


def test_grid_flags_a_bias_between_states(params, grid_bank):
    conv = make_converter("grid", None, bank=grid_bank)
    out = convert_points(conv, params, np.array([0.5e-12]), np.array([0.1]), np.array([0.0]), np.array([0.98]))
    assert np.all(out.flags == fl.OUT_OF_TABLE | fl.ENV_OUT_OF_RANGE)
    assert np.all(np.isnan(out.p_opt_w))


# --- flags: one helper builds counts for a chosen resistance ----------------------------

def counts_at_r(p, r_ohm, b=0.0, v=None):
    v = p.v_thev_v if v is None else v
    c = (model.tes_current_a(p, r_ohm, v) + p.pickup_a_per_t * b) / p.gain_a_per_count
    return np.rint(c.real).astype(np.int32), np.rint(c.imag).astype(np.int32)


ALL_KINDS = ("table", "grid", "exact", "linear", "electrical")


def converter(kind, params, bank, grid_bank, backend="numba"):
    if kind == "table":
        return make_converter(kind, None, bank=bank, backend=backend)
    if kind == "grid":
        return make_converter(kind, None, bank=grid_bank, backend=backend)
    return make_converter(kind, params)


@pytest.mark.parametrize("kind,backend", [(k, "numba") for k in ALL_KINDS] + [("table", "numpy"), ("grid", "numpy")])
def test_every_flag_is_set_where_it_belongs(params, bank, grid_bank, kind, backend):
    p = params["b0m0c099"]
    lo, hi = bank.r_range_ohm()[list(params).index("b0m0c099")]
    r_n = p.r_normal_ohm
    # Columns: ok, normal, latched, in branch below the table, NaN-free rail, zero current,
    # NaN field, bath <= 0, stale (value kept), missing (NaN env, no INVALID), env out of range.
    r = np.array([0.7, 1.2, 0.02, 0.5 * (lo + 0.071), 0.7, 0.7, 0.7, 0.7, 0.7, 0.7, 0.7]) * r_n
    ci, cq = counts_at_r(p, r)
    ci[4] = np.iinfo(np.int32).min
    ci[5] = cq[5] = 0
    tb = np.full(r.size, 0.1)
    b = np.zeros(r.size)
    b[6] = np.nan
    tb[7] = -0.1
    tb[9] = b[9] = np.nan
    tb[10] = 0.115
    hk = np.zeros(r.size, np.uint16)
    hk[8] = fl.HK_STALE
    hk[9] = fl.HK_MISSING
    ids = ["b0m0c099", "nope"]
    env = EnvironmentBlock(tb, b, flags=hk)
    conv = converter(kind, params, bank, grid_bank, backend)
    out = conv.convert(ids, np.stack([ci, ci]), np.stack([cq, cq]), env)
    f, pw = out.flags[0], out.p_opt_w[0]
    # The baselines flag outside their linearisation domain as the tables do outside theirs.
    table_kind = kind != "exact"
    expected = [
        0, fl.SATURATED, fl.SUPERCONDUCTING | fl.LATCHED, fl.OUT_OF_TABLE if table_kind else 0,
        fl.INVALID_INPUT, fl.INVALID_INPUT, fl.INVALID_INPUT, fl.INVALID_INPUT,
        fl.HK_STALE, fl.HK_MISSING, fl.ENV_OUT_OF_RANGE if table_kind else 0,
    ]
    # NONLINEAR (baselines' values off the exact inverse) has its own test; mask it here.
    assert [int(x) & ~fl.NONLINEAR for x in f] == expected
    usable = (f & fl.UNUSABLE) == 0
    assert np.all(np.isfinite(pw[usable])) and np.all(np.isnan(pw[~usable]))
    # Unknown detector: the whole row, with the housekeeping flags kept.
    assert np.all(out.flags[1] == fl.UNKNOWN_CHANNEL | hk) and np.all(np.isnan(out.p_opt_w[1]))
    assert out.identity == conv.identity and isinstance(conv, Converter)


def test_structured_table_stays_exact_outside_the_env_domain(params, bank):
    """Bath temperature and field are exact in the structured table: flagged, but right."""
    p = params["b0m0c099"]
    ci, cq = counts_at_r(p, np.array([0.6, 0.7, 0.8]))
    env = EnvironmentBlock(np.array([0.085, 0.1, 0.12]), np.array([0.0, 3e-4, 0.0]))
    ex = make_converter("exact", params).convert(["b0m0c099"], ci[None], cq[None], env)
    tb = make_converter("table", None, bank=bank).convert(["b0m0c099"], ci[None], cq[None], env)
    assert np.all(tb.flags == fl.ENV_OUT_OF_RANGE)
    assert np.abs(tb.p_opt_w - ex.p_opt_w).max() <= TARGET_W


@pytest.mark.parametrize("backend", BACKENDS)
def test_large_transition_shifts_leave_the_series_for_the_exact_power(backend):
    """|delta / T_s| > 0.05 (a 12 mK field shift here) takes the exact-power branch."""
    p = table1_params("b0m0c007", t_c_shift_k_per_t=60.0)
    params = {p.detector_id: p}
    bank = build_bank(params)
    b = np.array([-2e-4, -1e-4, 0.0, 1.5e-4, 2e-4])
    ci, cq = forward_counts(p, np.full(5, 0.4e-12), np.full(5, 0.1), b, p.v_thev_v)
    env = EnvironmentBlock(np.full(5, 0.1), b)
    ex = make_converter("exact", params).convert([p.detector_id], ci[None], cq[None], env)
    tb = make_converter("table", None, bank=bank, backend=backend).convert([p.detector_id], ci[None], cq[None], env)
    assert np.all(tb.flags == 0)
    assert np.abs(tb.p_opt_w - ex.p_opt_w).max() <= TARGET_W


@pytest.mark.parametrize("backend", BACKENDS)
def test_backends_agree_on_a_realistic_block(params, bank, backend):
    from mntes_stream.bench.convert import synthetic_block

    ids, ci, cq, env = synthetic_block(params, 300, seed=5, bad_fraction=0.02)
    hk = np.where(np.arange(300) % 37 == 0, fl.HK_STALE, 0).astype(np.uint16)
    env = EnvironmentBlock(env.t_bath_k, env.b_field_t, env.v_thev_v, hk)
    ref = make_converter("exact", params).convert(ids, ci, cq, env)
    out = make_converter("table", None, bank=bank, backend=backend).convert(ids, ci, cq, env)
    assert np.array_equal(out.flags, ref.flags)
    assert np.array_equal(np.isnan(out.p_opt_w), np.isnan(ref.p_opt_w))
    assert np.nanmax(np.abs(out.p_opt_w - ref.p_opt_w)) <= TARGET_W
    assert np.count_nonzero(out.flags & fl.INVALID_INPUT) > 0


@pytest.mark.skipif(not numba_available(), reason="numba not installed")
def test_a_samples_value_does_not_depend_on_its_row_or_neighbours(params, bank):
    """The compiled kernel runs a row as vector lanes, its remainder as scalar code, and lanes
    that need a branch (here: a bath beyond the series' 5%, exact power) by the reference: a
    sample's power and flags are the same bit for bit whichever of these computed it."""
    from mntes_stream.bench.convert import synthetic_block

    n = 41
    ids, ci, cq, env = synthetic_block(params, n, seed=9, bad_fraction=0.05)
    rng = np.random.default_rng(4)
    shape = ci.shape
    tb = np.where(rng.random(shape) < 0.3, 0.1075, np.broadcast_to(env.t_bath_k, shape))  # 7.5%: exact
    cq = np.where(rng.random(shape) < 0.1, cq * 3, cq).astype(np.int32)  # off the model: flags
    e = EnvironmentBlock(tb, np.broadcast_to(env.b_field_t, shape), env.v_thev_v)
    conv = make_converter("table", None, bank=bank, backend="numba")
    whole = conv.convert(ids, ci, cq, e)
    exact = make_converter("exact", params).convert(ids, ci, cq, e)
    clean = whole.flags == 0
    assert np.max(np.abs(whole.p_opt_w - exact.p_opt_w)[clean]) <= TARGET_W
    assert np.count_nonzero(clean & (tb > 0.105)) > 20
    assert np.count_nonzero(whole.flags & fl.OUT_OF_TABLE) and np.count_nonzero(whole.flags & fl.INVALID_INPUT)
    for width in (1, 5, 8, 15, 16, 17, 33):
        for s0 in (0, 3, n - width):
            part = conv.convert(ids, ci[:, s0:s0 + width], cq[:, s0:s0 + width],
                                EnvironmentBlock(tb[:, s0:s0 + width], e.b_field_t[:, s0:s0 + width], e.v_thev_v))
            assert np.array_equal(part.p_opt_w, whole.p_opt_w[:, s0:s0 + width], equal_nan=True), (width, s0)
            assert np.array_equal(part.flags, whole.flags[:, s0:s0 + width]), (width, s0)


@pytest.mark.skipif(not numba_available(), reason="numba not installed")
def test_a_converter_pickled_before_the_record_converts_the_same(params, bank):
    """A converter restored from an older snapshot holds the old per-detector constants (``_pre``,
    no ``_rec``): it builds the record on first use and converts as a new one."""
    from mntes_stream.bench.convert import synthetic_block

    ids, ci, cq, env = synthetic_block(params, 30, seed=2)
    conv = make_converter("table", None, bank=bank, backend="numba")
    ref = conv.convert(ids, ci, cq, env)
    state = {k: v for k, v in conv.__dict__.items() if k != "_rec"}
    state["_pre"] = np.zeros((len(bank), 10))  # the layout before the record
    old = object.__new__(type(conv))
    old.__setstate__(state)  # as unpickling does
    out = old.convert(ids, ci, cq, env)
    assert np.array_equal(out.p_opt_w, ref.p_opt_w, equal_nan=True) and np.array_equal(out.flags, ref.flags)


def test_environment_layouts_are_equivalent(params, bank):
    """Shared (n_samp,) and per-detector (n_det, n_samp) environment give the same result."""
    from mntes_stream.bench.convert import synthetic_block

    ids, ci, cq, env = synthetic_block(params, 50, seed=6, bad_fraction=0.0)
    conv = make_converter("table", None, bank=bank)
    shape = ci.shape
    a = conv.convert(ids, ci, cq, env)
    full = EnvironmentBlock(np.tile(env.t_bath_k, (shape[0], 1)), np.tile(env.b_field_t, (shape[0], 1)),
                            np.repeat(env.v_thev_v[:, None], shape[1], axis=1), np.zeros(shape, np.uint16))
    b = conv.convert(ids, ci, cq, full)
    c = conv.convert(ids, ci.astype(np.float64), cq.astype(np.int64), env)  # other count types
    assert np.array_equal(a.p_opt_w, b.p_opt_w, equal_nan=True) and np.array_equal(a.flags, b.flags)
    assert np.array_equal(a.p_opt_w, c.p_opt_w, equal_nan=True)
    # v_thev_v None means each detector's nominal bias.
    nominal = EnvironmentBlock(env.t_bath_k, env.b_field_t)
    explicit = EnvironmentBlock(env.t_bath_k, env.b_field_t, np.array([q.v_thev_v for q in params.values()]))
    assert np.array_equal(conv.convert(ids, ci, cq, nominal).p_opt_w, conv.convert(ids, ci, cq, explicit).p_opt_w,
                          equal_nan=True)


@pytest.mark.skipif(not numba_available(), reason="numba not installed")
def test_no_layout_of_the_inputs_compiles_the_kernel_again(params, bank, grid_bank):
    """Read-only message views, slices, broadcast environments and float counts all run on the two
    signatures compiled before the first conversion: a live chunk never waits seconds for numba."""
    from mntes_stream.bench.convert import synthetic_block
    from mntes_stream.core import _kernels

    ids, ci, cq, env = synthetic_block(params, 40, seed=8, bad_fraction=0.0)
    ro_i = np.frombuffer(ci.tobytes(), dtype=np.int32).reshape(ci.shape)  # as decoded from a message
    ro_q = np.frombuffer(cq.tobytes(), dtype=np.int32).reshape(cq.shape)
    n = len(ids)
    layouts = [
        (ids, ci, cq, env),
        (ids, ro_i, ro_q, env),
        (ids[:1], ro_i[:1, :2], ro_q[:1, :2], EnvironmentBlock(env.t_bath_k[:2], env.b_field_t[:2])),  # warm-up shape
        (ids, ci[:, ::2], cq[:, ::2], EnvironmentBlock(env.t_bath_k[::2], env.b_field_t[::2], env.v_thev_v)),
        (ids, ci.astype(float), cq.astype(float), env),
        (ids, ci, cq, EnvironmentBlock(np.tile(env.t_bath_k, (n, 1)), np.tile(env.b_field_t, (n, 1)),
                                       np.repeat(env.v_thev_v[:, None], ci.shape[1], axis=1),
                                       np.zeros(ci.shape, np.uint16))),
    ]
    for b in (bank, grid_bank):
        conv = make_converter(b.kind, None, bank=b, backend="numba")
        twin = make_converter(b.kind, None, bank=b, backend="numpy")
        for lid, li, lq, lenv in layouts:
            out, ref = conv.convert(lid, li, lq, lenv), twin.convert(lid, li, lq, lenv)
            assert np.array_equal(out.flags, ref.flags)
            assert np.allclose(out.p_opt_w, ref.p_opt_w, rtol=0, atol=TARGET_W, equal_nan=True)
    assert len(_kernels._table_kernel.signatures) == 2 and len(_kernels._grid_kernel.signatures) == 2

def test_float_counts_may_carry_nan(params, bank):
    ci = np.array([[1.0e6, np.nan, np.inf]])
    cq = np.zeros_like(ci)
    out = make_converter("table", None, bank=bank).convert(["b0m0c099"], ci, cq, EnvironmentBlock(np.full(3, 0.1), np.zeros(3)))
    assert list(out.flags[0, 1:]) == [fl.INVALID_INPUT, fl.INVALID_INPUT]
    assert np.all(np.isnan(out.p_opt_w[0, 1:]))


@pytest.mark.skipif(not numba_available(), reason="numba not installed")
def test_rows_with_a_bad_first_or_last_sample_convert_as_the_numpy_twin(params, bank):
    """The compiled kernel prefetches each block of rows' table lines from every row's first and
    last sample (``_kernels._prefetch_block``): a NaN, infinite, railed or off-table sample there,
    or an unknown detector, still converts as the numpy twin does, over more rows than one block."""
    from mntes_stream.bench.convert import synthetic_block
    from mntes_stream.core import _kernels

    ids, ci, cq, env = synthetic_block(params, 7, seed=12, bad_fraction=0.0)
    reps = _kernels._BLOCK // (len(ids) + 1) + 2
    rows = np.arange(reps * (len(ids) + 1)) % (len(ids) + 1)  # the last of each group: unknown
    known = rows < len(ids)
    k = np.minimum(rows, len(ids) - 1)
    all_ids = [ids[j] if ok else "nobody" for j, ok in zip(k, known)]
    ci, cq = ci[k].astype(np.float64), cq[k].astype(np.float64)
    n = np.arange(len(rows))
    ci[n % 3 == 0, 0] = np.nan
    ci[n % 5 == 0, -1] = np.inf
    ci[n % 7 == 1, 0] *= 10.0   # R far off the table
    cq[n % 11 == 2, -1] = 2.0**31
    ci[n % 4 == 3, -1] *= 0.5
    e = EnvironmentBlock(env.t_bath_k, env.b_field_t, np.where(known, env.v_thev_v[k], 1.0))
    conv = make_converter("table", None, bank=bank, backend="numba")
    out = conv.convert(all_ids, ci, cq, e)
    ref = make_converter("table", None, bank=bank, backend="numpy").convert(all_ids, ci, cq, e)
    assert len(rows) > _kernels._BLOCK
    assert np.array_equal(out.flags, ref.flags)
    assert np.allclose(out.p_opt_w, ref.p_opt_w, rtol=0, atol=TARGET_W, equal_nan=True)
    for flag in (fl.INVALID_INPUT, fl.UNKNOWN_CHANNEL, fl.OUT_OF_TABLE | fl.SATURATED | fl.SUPERCONDUCTING):
        assert np.count_nonzero(out.flags[:, [0, -1]] & flag), flag
    assert np.count_nonzero(out.flags == 0) > len(rows)
    # The cell it prefetches from is the detector's own whatever the sample, as the kernel then
    # reads it: int(NaN) is undefined (INT64_MIN on x86), so a NaN R must never reach it.
    rec = conv._row_constants()
    for d in range(len(ids)):
        first, n_cell = rec[d, _kernels._R_C0], rec[d, _kernels._R_NCELL]
        for xi in (np.nan, np.inf, -np.inf, 2.0**31, ci[d, 1], 10 * ci[d, 1], 0.1 * ci[d, 1], -ci[d, 1]):
            cell = _kernels._cell_of(float(xi), float(cq[d, 1]), 0.0, float(env.v_thev_v[d]), rec, d)
            assert first <= cell < first + n_cell, (d, xi)


# --- linear baselines against independent expectations ----------------------------------

def test_linear_is_exact_at_the_operating_point_and_second_order_away(params):
    p = params["b0m0c099"]
    conv = make_converter("linear", {p.detector_id: p})
    op = model.solve_operating_point(p, p.p_opt_w)
    ss = model.small_signal(p, op.r_ohm)
    dp = np.array([0.0, 1e-15, -1e-15, 2e-15])
    ci, cq = forward_counts(p, p.p_opt_w + dp, p.t_bath_k, 0.0, p.v_thev_v, rounded=False)
    out = conv.convert([p.detector_id], ci[None], cq[None], EnvironmentBlock(np.full(4, p.t_bath_k), np.zeros(4)))
    err = out.p_opt_w[0] - (p.p_opt_w + dp)
    assert abs(err[0]) < 1e-24
    # Leading order: P_lin - P = Re(i''/S) dP^2 / 2, from the exact second derivative.
    predicted = 0.5 * np.real(ss.d2i_dp2_a_per_w2 / ss.responsivity_a_per_w) * dp[1:] ** 2
    np.testing.assert_allclose(err[1:], predicted, rtol=0.02)


def test_electrical_is_total_power_minus_joule_power(params):
    p = params[list(params)[0]]
    conv = make_converter("electrical", {p.detector_id: p})
    p_w = np.array([0.1e-12, 0.5e-12, 0.9e-12])
    tb, b, v = np.full(3, 0.1), np.array([0.0, 5e-5, -5e-5]), 1.02 * p.v_thev_v
    op = model.solve_operating_point(p, p_w, tb, b, v)
    ci, cq = forward_counts(p, p_w, tb, b, v, rounded=False)
    out = conv.convert([p.detector_id], ci[None], cq[None], EnvironmentBlock(tb, b, np.array([v])))
    op0 = model.solve_operating_point(p, p.p_opt_w)
    p_total = p.p_opt_w + model.joule_power_w(p, op0.r_ohm)
    # The measured current includes the pickup, which this baseline does not know about.
    i_meas = model.readout_current_a(p, op.i_a, b) / np.sqrt(2)
    p_el = np.real((v - p.z_thev_ohm * i_meas) * np.conj(i_meas))
    np.testing.assert_allclose(out.p_opt_w[0], p_total - p_el, rtol=0, atol=1e-26)
    # Without pickup it is exactly the Joule power of the TES.
    np.testing.assert_allclose(p_el[0], model.joule_power_w(p, op.r_ohm[0], v), rtol=1e-12)


def test_linear_flags_nonlinear_where_it_leaves_the_exact_inverse_and_keeps_the_value(params):
    """NONLINEAR exactly where |P_lin - P_exact| > tolerance, P_exact from model.invert_current on the same counts."""
    p = params["b0m0c099"]
    dp = np.array([0.0, 1e-15, -2e-15, 1e-13, -1e-13, 0.3e-12, -0.3e-12])
    n = dp.size
    ci, cq = forward_counts(p, p.p_opt_w + dp, p.t_bath_k, 0.0, p.v_thev_v)
    env = EnvironmentBlock(np.full(n, p.t_bath_k), np.zeros(n))
    out = make_converter("linear", {p.detector_id: p}).convert([p.detector_id], ci[None], cq[None], env)
    off = make_converter("linear", {p.detector_id: p}, tolerance_w=None).convert(
        [p.detector_id], ci[None], cq[None], env)
    exact = model.invert_current(p, p.gain_a_per_count * (ci + 1j * cq), p.t_bath_k, 0.0, p.v_thev_v).p_opt_w
    f, pw = out.flags[0], out.p_opt_w[0]
    hit = (f & fl.NONLINEAR) != 0
    # Second order in dP (about 0.8/pW here): 1e-15 W off nominal is ~4e-19 W wrong, 1e-13 W ~4e-15 W.
    assert not hit[:3].any() and hit[3:].all()
    np.testing.assert_array_equal(hit, np.abs(pw - exact) > 1e-17)
    assert np.all((f | fl.NONLINEAR) == fl.NONLINEAR)  # no other bit
    # A warning: the value is kept, and is the unchecked conversion's.
    assert np.all(np.isfinite(pw)) and np.array_equal(pw, off.p_opt_w[0]) and not np.any(off.flags)
    # The baseline ignores the bath: 1 mK off nominal at the operating point is far beyond 1e-17 W.
    ci2, cq2 = forward_counts(p, np.array([p.p_opt_w]), p.t_bath_k + 1e-3, 0.0, p.v_thev_v)
    env2 = EnvironmentBlock(np.array([p.t_bath_k + 1e-3]), np.zeros(1))
    for kind in ("linear", "electrical"):
        out2 = make_converter(kind, {p.detector_id: p}).convert([p.detector_id], ci2[None], cq2[None], env2)
        assert out2.flags[0, 0] == fl.NONLINEAR and np.isfinite(out2.p_opt_w[0, 0])
    with pytest.raises(ConfigError, match="tolerance_w"):
        make_converter("linear", {p.detector_id: p}, tolerance_w=-1.0)


# --- bad input ----------------------------------------------------------------------------

@pytest.mark.parametrize("kind", ALL_KINDS)
def test_wrong_shapes_and_dtypes_raise_schema_errors(params, bank, grid_bank, kind):
    conv = converter(kind, params, bank, grid_bank)
    ids = list(params)[:2]
    ci = np.ones((2, 5), np.int32)
    env = EnvironmentBlock(np.full(5, 0.1), np.zeros(5))
    bad = [
        (ids, ci[0], ci[0], env),                                   # 1-D counts
        (ids, ci, np.ones((2, 4), np.int32), env),                  # I/Q shapes differ
        (ids[:1], ci, ci, env),                                      # ids do not match rows
        (ids, ci.astype(complex), ci, env),                          # complex counts
        (ids, ci.tolist(), ci, env),                                 # not an array
        (ids, ci, ci, EnvironmentBlock(np.full(4, 0.1), np.zeros(5))),        # t_bath length
        (ids, ci, ci, EnvironmentBlock(np.full((3, 5), 0.1), np.zeros(5))),   # t_bath rows
        (ids, ci, ci, EnvironmentBlock(np.full(5, 0.1), np.zeros(5), np.ones(5))),  # bias must be (n_det,)
        (ids, ci, ci, EnvironmentBlock(np.full(5, 0.1), np.zeros(5), flags=np.zeros(5))),  # float flags
        (ids, ci, ci, EnvironmentBlock(np.array(["a"] * 5), np.zeros(5))),    # strings
        (ids, ci, ci, {"t_bath_k": 0.1}),                                      # not an EnvironmentBlock
    ]
    for args in bad:
        with pytest.raises(SchemaError):
            conv.convert(*args)


def test_make_converter_rejects_bad_configuration(params, bank, grid_bank):
    with pytest.raises(ConfigError, match="unknown converter kind"):
        make_converter("magic", params)
    with pytest.raises(ConfigError, match="no table bank"):
        make_converter("exact", params, bank=bank)
    with pytest.raises(ConfigError, match="is of kind"):
        make_converter("table", None, bank=grid_bank)
    other = {k: v.replace(n=v.n + 0.01) for k, v in params.items()}
    with pytest.raises(ConfigError, match="other parameters"):
        make_converter("table", other, bank=bank)
    with pytest.raises(ConfigError, match="no table for detector"):
        make_converter("table", {"b9m9c999": table1_params("b9m9c999")}, bank=bank)
    with pytest.raises(ConfigError, match="backend"):
        make_converter("table", None, bank=bank, backend="fortran")
    with pytest.raises(ConfigError, match="build options"):
        make_converter("table", None, bank=bank, p_tol_w=1e-20)
    with pytest.raises(ConfigError, match="needs params"):
        make_converter("linear", None)


def test_identity_travels_and_tracks_parameters(params, bank):
    conv = make_converter("table", params, bank=bank)
    assert conv.identity == bank.identity and len(conv.identity) == 64
    out = conv.convert(list(params)[:1], np.ones((1, 2), np.int32), np.ones((1, 2), np.int32),
                       EnvironmentBlock(np.full(2, 0.1), np.zeros(2)))
    assert isinstance(out, PowerBlock) and out.identity == bank.identity
    kinds = {make_converter(k, params).identity for k in ("exact", "linear", "electrical")}
    assert len(kinds) == 3
    changed = dict(params, b0m0c099=params["b0m0c099"].replace(k_w_per_k_n=7e-10))
    assert make_converter("exact", changed).identity != make_converter("exact", params).identity
    small = build_bank(params, kind="table", domain=TableDomain(p_opt_w=(0.1e-12, 0.9e-12)))
    assert small.identity != bank.identity


def test_non_string_ids_are_unknown_channels(params, bank):
    conv = make_converter("table", None, bank=bank)
    p = params["b0m0c099"]
    ci, cq = counts_at_r(p, np.array([0.7, 0.7]))
    env = EnvironmentBlock(np.full(2, 0.1), np.zeros(2))
    for ids in (["b0m0c099", ["b0m0c099"]], ["b0m0c099", 7]):
        out = conv.convert(ids, np.stack([ci, ci]), np.stack([cq, cq]), env)
        assert np.all(out.flags[0] == 0) and np.all(out.flags[1] == fl.UNKNOWN_CHANNEL)

"""The baselines' compiled kernel (core._baselines) against the numpy expressions it replaced."""

from __future__ import annotations

import numpy as np
import pytest

from mntes_stream.bench.convert import synthetic_block, synthetic_params
from mntes_stream.core import _baselines, _kernels
from mntes_stream.core import flags as fl
from mntes_stream.core.convert import SQRT2, EnvironmentBlock, _prepare, make_converter
from mntes_stream.errors import ConfigError

pytestmark = pytest.mark.skipif(not _baselines.available(), reason="numba not installed")


@pytest.fixture(scope="module")
def case():
    params = synthetic_params(12, seed=5)
    ids, ci, cq, env = synthetic_block(params, 400, seed=6, bad_fraction=0.01)
    ids = list(ids)
    ids[3] = "nobody"  # an unknown channel: whole row flagged, NaN
    return params, ids, ci, cq, env


def _reference(conv, ids, ci, cq, env):
    """Previous implementation, written out: front end in numpy, the kind's complex expression."""
    kind = conv.kind
    rows = np.array([conv.detector_ids.index(d) if d in conv.detector_ids else -1 for d in ids])
    shape = ci.shape
    tb = np.broadcast_to(np.asarray(env.t_bath_k, float), shape)
    b = np.broadcast_to(np.asarray(env.b_field_t, float), shape)
    v = np.broadcast_to(np.asarray(env.v_thev_v, float)[:, None], shape)
    hk = np.broadcast_to(np.zeros((), np.uint16) if env.flags is None else np.asarray(env.flags, np.uint16), shape)
    r, _, f, _, ok = _kernels.front_numpy(ci, cq, tb, b, v, hk, rows, conv._phys, conv._dom)
    k = np.maximum(rows, 0)
    rr = conv._r_range[k]
    with np.errstate(invalid="ignore"):
        f[ok & ~((r >= rr[:, :1]) & (r <= rr[:, 1:]))] |= fl.OUT_OF_TABLE
    gain = (conv._phys[k, 0] + 1j * conv._phys[k, 1])[:, None]
    i = gain * (np.asarray(ci, float) + 1j * np.asarray(cq, float))
    with np.errstate(all="ignore"):
        if kind == "linear":
            p = conv.p0_w[k, None] + np.real((i - conv.i0_a[k, None]) / conv.responsivity_a_per_w[k, None])
        else:
            z = (conv._phys[k, 4] + 1j * conv._phys[k, 5])[:, None]
            i_rms = i / SQRT2
            p = conv.p_total_w[k, None] - np.real((v - z * i_rms) * np.conj(i_rms))
    p[(f & fl.UNUSABLE) != 0] = np.nan
    return p, f


@pytest.mark.parametrize("kind", ["linear", "electrical"])
@pytest.mark.parametrize("layout", ["shared", "per-sample", "float-counts"])
def test_kernel_equals_the_numpy_expressions(case, kind, layout):
    """Values within 1 ulp (bit for bit where the CPU has FMA, as numpy's complex product uses it),
    flags identical, NaN exactly where unusable; every environment layout the converters see."""
    params, ids, ci, cq, env = case
    n_det, n_samp = ci.shape
    hk = np.zeros(n_samp, np.uint16)
    hk[::37] = fl.HK_STALE
    hk[5] = fl.HK_MISSING
    tb = np.array(env.t_bath_k)
    tb[7] = -1.0  # not > 0: INVALID_INPUT, except where HK_MISSING says so already
    tb[5] = np.nan
    if layout == "per-sample":
        rng = np.random.default_rng(1)
        tb = np.tile(tb, (n_det, 1)) * (1 + 1e-3 * rng.normal(size=(n_det, n_samp)))
        env = EnvironmentBlock(tb, np.tile(env.b_field_t, (n_det, 1))[:, ::-1], env.v_thev_v, np.tile(hk, (n_det, 1)))
    else:
        env = EnvironmentBlock(tb, env.b_field_t, env.v_thev_v, hk)
    if layout == "float-counts":
        ci = ci.astype(float)
        ci[1, 10] = np.nan
        ci[2, 11] = -np.inf
    conv = make_converter(kind, params, tolerance_w=None)
    out = conv.convert(ids, ci, cq, env)
    p_ref, f_ref = _reference(conv, ids, ci, cq, env)
    np.testing.assert_array_equal(out.flags, f_ref)
    assert np.array_equal(np.isnan(out.p_opt_w), np.isnan(p_ref))
    np.testing.assert_array_max_ulp(np.nan_to_num(out.p_opt_w), np.nan_to_num(p_ref), maxulp=1)
    # Enough of everything that the comparison means something.
    assert np.count_nonzero(out.flags & fl.UNKNOWN_CHANNEL) == n_samp
    assert np.count_nonzero(out.flags & fl.INVALID_INPUT) > n_det
    assert np.count_nonzero(np.isfinite(out.p_opt_w)) > 0.5 * out.p_opt_w.size


@pytest.mark.parametrize("kind", ["linear", "electrical"])
def test_nonlinear_and_values_identical_to_the_numpy_route(case, kind):
    """With the NONLINEAR check on (the default), the compiled route gives the numpy route's
    flags and values exactly (the check itself is unchanged: the exact inverse per usable sample)."""
    params, ids, ci, cq, env = case
    conv = make_converter(kind, params)
    out = conv.convert(ids, ci, cq, env)
    inp = _prepare(conv._rows, conv._v_nominal, ids, ci, cq, env)
    p = np.empty(ci.shape)
    f = np.empty(ci.shape, np.uint16)
    conv._convert_numpy(inp, p, f)
    np.testing.assert_array_equal(out.flags, f)
    np.testing.assert_array_max_ulp(np.nan_to_num(out.p_opt_w), np.nan_to_num(p), maxulp=1)
    assert np.count_nonzero(out.flags & fl.NONLINEAR) > 0


@pytest.mark.parametrize("kind", ["linear", "electrical"])
def test_nonlinear_from_the_table_equals_the_exact_check(kind):
    """The default check (the table's power, the exact inverse near the tolerance) flags exactly
    the samples the exact inverse does, on loading swept across the tolerance, in live-size chunks."""
    from mntes_stream.core.tables import TableDomain

    params = synthetic_params(6, seed=8)
    ids, ci, cq, env = synthetic_block(params, 600, seed=9, bad_fraction=0.0)
    # The bath held at nominal and the field at zero, so the baselines' error is their
    # non-linearity alone: small near the operating point, above 1e-17 W away from it.
    env = EnvironmentBlock(np.full(600, 0.100), np.zeros(600), env.v_thev_v * 0 + [q.v_thev_v for q in params.values()])
    table = make_converter(kind, params, domain=TableDomain())
    exact = make_converter(kind, params, domain=TableDomain(), nonlinear_check="exact")
    assert (table.nonlinear_check, exact.nonlinear_check) == ("table", "exact")
    for s in range(0, 600, 20):
        a = table.convert(ids, ci[:, s:s + 20], cq[:, s:s + 20], EnvironmentBlock(
            env.t_bath_k[s:s + 20], env.b_field_t[s:s + 20], env.v_thev_v))
        b = exact.convert(ids, ci[:, s:s + 20], cq[:, s:s + 20], EnvironmentBlock(
            env.t_bath_k[s:s + 20], env.b_field_t[s:s + 20], env.v_thev_v))
        np.testing.assert_array_equal(a.flags, b.flags)
        np.testing.assert_array_equal(a.p_opt_w, b.p_opt_w)
    whole = table.convert(ids, ci, cq, env)
    hit = (whole.flags & fl.NONLINEAR) != 0
    assert 0.05 < hit.mean() < 0.95, hit.mean()  # both sides of the tolerance are exercised


def test_nonlinear_check_option_is_validated_and_off_builds_nothing():
    params = synthetic_params(2, seed=1)
    with pytest.raises(ConfigError, match="nonlinear_check"):
        make_converter("linear", params, nonlinear_check="approximate")
    assert make_converter("electrical", params, tolerance_w=None).nonlinear_check == "off"

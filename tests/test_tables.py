"""Response tables: interpolation accuracy, exact coverage, one-file banks with identity, CLI."""

from __future__ import annotations

import json

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from mntes_stream.bench.convert import synthetic_params, tabulated_params
from mntes_stream.cli import main
from mntes_stream.core import model
from mntes_stream.core.convert import EnvironmentBlock, make_converter
from mntes_stream.core.params import table1_params
from mntes_stream.core.tables import (
    TableBank,
    TableDomain,
    build_bank,
    cell_floor,
    grid_bank_from_curves,
    hermite_coefficients,
    lookup_cells,
    resistance_range_ohm,
    transition_knots,
)
from mntes_stream.errors import ConfigError, SchemaError
from mntes_stream.io.paramfile import dump_params
from mntes_stream.io.tablefile import load_bank, read_header, save_bank


@pytest.fixture(scope="module")
def params():
    out = synthetic_params(3, seed=21)
    tab = tabulated_params("b0m0c050")
    out[tab.detector_id] = tab
    return out


@pytest.fixture(scope="module")
def bank(params):
    return build_bank(params)


def eval_table(x, c, r):
    j = np.clip(np.searchsorted(x, r, side="right") - 1, 0, x.size - 2)
    s = r - x[j]
    return c[j, 0] + s * (c[j, 1] + s * (c[j, 2] + s * c[j, 3]))


def test_hermite_pieces_reproduce_cubics_exactly():
    x = np.array([0.0, 0.3, 0.35, 1.0])
    f = lambda r: 2.0 - r + 3.0 * r**2 - 0.5 * r**3  # noqa: E731
    df = lambda r: -1.0 + 6.0 * r - 1.5 * r**2  # noqa: E731
    c = hermite_coefficients(x, f(x), df(x))
    r = np.linspace(0, 1, 101)
    np.testing.assert_allclose(eval_table(x, c, r), f(r), rtol=0, atol=1e-14)


@pytest.mark.parametrize("which", ["arctan", "tabulated"])
def test_response_table_meets_its_tolerances(params, which):
    """W = K T_s^n within p_tol and T_s (from U = 1/T_s) within t_tol, densely between knots."""
    p = next(q for q in params.values() if (q.transition.kind == which))
    r_lo, r_hi = resistance_range_ohm(p, TableDomain())
    p_tol, t_tol = 1e-21, 1e-11
    x, c = transition_knots(p, r_lo, r_hi, p_tol, t_tol)
    r = np.linspace(r_lo, r_hi, 200_001)
    t = p.transition.temperature_k(r)
    assert np.abs(eval_table(x, c[:, :4], r) - p.k_w_per_k_n * t**p.n).max() < p_tol
    assert np.abs(1.0 / eval_table(x, c[:, 4:], r) - t).max() < t_tol
    if which == "tabulated":  # every measured point inside the range is a knot
        pts = np.asarray(p.transition.r_ohm)
        assert np.all(np.isin(pts[(pts > r_lo) & (pts < r_hi)], x))


def test_resistance_range_is_exactly_what_the_domain_reaches(params):
    """Random env points inside the domain stay inside [r_lo, r_hi]; the two extreme corners touch it."""
    domain = TableDomain(p_opt_w=(0.05e-12, 1.0e-12), t_bath_k=(0.095, 0.105), b_field_t=(-1e-4, 1e-4),
                         v_frac=(0.95, 1.05))
    rng = np.random.default_rng(4)
    for p in params.values():
        r_lo, r_hi = resistance_range_ohm(p, domain)
        n = 400
        op = model.solve_operating_point(
            p, rng.uniform(*domain.p_opt_w, n), rng.uniform(*domain.t_bath_k, n),
            rng.uniform(*domain.b_field_t, n), p.v_thev_v * rng.uniform(*domain.v_frac, n),
        )
        assert np.all((op.r_ohm >= r_lo) & (op.r_ohm <= r_hi))
        # Lowest R: least power, coldest bath, lowest bias, largest T_c shift. Highest: the opposite.
        b = np.linspace(*domain.b_field_t, 2001)
        shift = p.t_c_shift_k_per_t * b + p.t_c_shift_k_per_t2 * b * b
        lo = model.solve_operating_point(p, domain.p_opt_w[0], 0.095, b[np.argmax(shift)], 0.95 * p.v_thev_v)
        hi = model.solve_operating_point(p, domain.p_opt_w[1], 0.105, b[np.argmin(shift)], 1.05 * p.v_thev_v)
        assert abs(float(lo.r_ohm) - r_lo) < 1e-6 and abs(float(hi.r_ohm) - r_hi) < 1e-6


@settings(max_examples=50, deadline=None)
@given(st.lists(st.floats(1e-6, 1.0), min_size=2, max_size=40), st.floats(0.0, 1.0))
def test_lookup_cells_find_the_right_interval(widths, u):
    x = np.concatenate([[0.0], np.cumsum(widths)])
    cells, per = lookup_cells(x, max_cells_per_interval=4)
    r = u * x[-1]
    cell = min(int((r - x[0]) * per), cells.size - 1)
    j = int(cells[cell])
    while j + 1 < x.size - 1 and r >= x[j + 1]:
        j += 1
    assert x[j] <= r and (r < x[j + 1] or j == x.size - 2)


@settings(max_examples=50, deadline=None)
@given(st.floats(-10.0, 10.0), st.floats(1e-3, 10.0), st.lists(st.integers(0, 2**20), min_size=1, max_size=20))
@example(-4.25, 10.0, [439092])  # r near 0, x0 far from it: a step of r's ulp may leave fl(r - x0) as it was
@example(-1.0, 2.0, [0, 2**19, 2**20])  # r through 0 and -0
def test_cell_floor_is_the_first_float_of_its_cell(x0, span, ks):
    """Smallest r with fl(fl(r - x0) * fl(1 / span)) >= t, checked against its neighbour below."""
    t = np.array(ks, dtype=float) / 2**20
    r = cell_floor(x0, span, t)
    u0 = 1.0 / span
    assert np.all((r - x0) * u0 >= t)
    assert np.all((np.nextafter(r, -np.inf) - x0) * u0 < t)
    # Cells of every power-of-two count begin there, by the kernels' own arithmetic.
    for n in (2**10, 2**20):
        assert np.all(((r - x0) * (n / span)).astype(np.int64) == np.floor(t * n))


@pytest.mark.parametrize("which", ["arctan", "tabulated"])
def test_knots_begin_lookup_cells_so_a_cell_needs_no_step(params, which):
    """transition_knots places its knots where lookup cells begin: once the cells are as narrow as the
    narrowest interval, every R (each knot, the float just below it, random R) finds its interval in its
    cell's entry, with no step, except in a cell holding a measured transition's joint."""
    p = next(q for q in params.values() if q.transition.kind == which)
    r_lo, r_hi = resistance_range_ohm(p, TableDomain())
    x, _ = transition_knots(p, r_lo, r_hi, 1e-20, 1e-11)
    cells, per = lookup_cells(x, max_cells_per_interval=1 << 12)
    assert per * np.min(np.diff(x)) >= 1.0  # cells resolve every interval
    rng = np.random.default_rng(0)
    r = np.concatenate([x[:-1], np.nextafter(x[1:-1], -np.inf), rng.uniform(r_lo, r_hi, 200_000)])
    cell = np.minimum(((r - x[0]) * per).astype(np.int64), cells.size - 1)
    truth = np.minimum(np.searchsorted(x, r, side="right") - 1, x.size - 2)
    assert np.all(cells[cell] <= truth)  # never past the interval: the kernels step only to the right
    pts = np.asarray(getattr(p.transition, "r_ohm", []), dtype=float)
    joints = pts[(pts > r_lo) & (pts < r_hi)]
    holds_joint = np.isin(cell, ((joints - x[0]) * per).astype(np.int64))
    assert np.array_equal(cells[cell] != truth, (cells[cell] != truth) & holds_joint)


def test_build_rejects_bad_input():
    with pytest.raises(ConfigError):
        build_bank({})
    with pytest.raises(ConfigError, match="unknown table kind"):
        build_bank([table1_params("b0m0c000")], kind="cubic")
    with pytest.raises(ConfigError, match="key"):
        build_bank({"x": table1_params("b0m0c000")})
    with pytest.raises(ConfigError):
        TableDomain(t_bath_k=(0.11, 0.09))
    with pytest.raises(ConfigError, match="above saturation"):  # a measured transition ends at R_n
        build_bank([tabulated_params()], domain=TableDomain(p_opt_w=(5e-12, 6e-12)))
    with pytest.raises(ConfigError, match="n_b_nodes"):
        build_bank([table1_params("b0m0c000")], kind="grid", n_b_nodes=3)


def test_bank_memory_scales_to_5000_detectors_under_1_gib(bank):
    assert bank.nbytes / len(bank) * 5000 < 2**30 / 4


# --- files ----------------------------------------------------------------------------------

def test_save_load_round_trip_keeps_identity_and_results(tmp_path, params, bank):
    path = save_bank(bank, tmp_path / "bank.npz")
    loaded = load_bank(path)
    assert loaded.identity == bank.identity
    assert loaded.params == bank.params and loaded.domain == bank.domain
    for name, a in bank.arrays.items():
        assert np.array_equal(loaded.arrays[name], a)
    for b in (bank, loaded):  # built or loaded, the kernel's lookups start on a cache line
        for name in ("r_knot_ohm", "cell_interval", "coeffs"):
            assert b.arrays[name].ctypes.data % 64 == 0 and not b.arrays[name].flags.writeable, name
    assert read_header(path)["identity"] == bank.identity
    ids = list(params)
    ci = np.full((len(ids), 3), 1_200_000, np.int32)
    env = EnvironmentBlock(np.full(3, 0.1), np.zeros(3))
    a = make_converter("table", None, bank=bank).convert(ids, ci, ci // 10, env)
    b = make_converter("table", params, bank=loaded).convert(ids, ci, ci // 10, env)
    assert np.array_equal(a.p_opt_w, b.p_opt_w, equal_nan=True) and b.identity == bank.identity


def test_grid_bank_round_trip_and_curves_constructor(tmp_path, params):
    grid = build_bank(params, kind="grid", n_power=64, n_b_nodes=5)
    loaded = load_bank(save_bank(grid, tmp_path / "grid.npz"))
    assert loaded.identity == grid.identity and loaded.kind == "grid"
    # The same curves handed in from outside give the same tables.
    ko = grid.arrays["knot_offset"]
    cut = lambda a: [a[ko[k]:ko[k + 1]] for k in range(len(grid))]  # noqa: E731
    again = grid_bank_from_curves(
        grid.params, cut(grid.arrays["r_knot_ohm"]), cut(grid.arrays["p_w"]), grid.arrays["bias_v"],
        grid.arrays["b_nodes_t"], grid.arrays["t_ref_k"], grid.domain, grid.options,
        dp_dr_w_per_ohm=cut(grid.arrays["dp_dr_w_per_ohm"]),
    )
    assert again.identity == grid.identity


def _edited_copy(src, dst, edit):
    """Rewrite a bank file with ``edit(members)`` applied to its decoded members."""
    with np.load(src) as npz:
        members = {name: npz[name].copy() for name in npz.files}
    edit(members)
    np.savez(dst, **members)
    return dst


def _header_version(members, version):
    doc = json.loads(bytes(members["__header__"]).decode())
    doc["version"] = version
    members["__header__"] = np.frombuffer(json.dumps(doc).encode(), dtype=np.uint8)


def test_corrupted_edited_and_foreign_files_are_refused(tmp_path, bank):
    good = save_bank(bank, tmp_path / "good.npz")
    raw = bytearray(good.read_bytes())

    truncated = tmp_path / "truncated.npz"
    truncated.write_bytes(raw[: len(raw) // 2])
    text = tmp_path / "text.npz"
    text.write_text("not a table file")
    flipped = tmp_path / "flipped.npz"
    raw[len(raw) // 2] ^= 0x40  # inside some member's data: the zip CRC or the hash must catch it
    flipped.write_bytes(bytes(raw))
    for path in (truncated, text, flipped):
        with pytest.raises(SchemaError):
            load_bank(path)

    def nudge(m):
        m["coeffs"][5, 0] = np.nextafter(m["coeffs"][5, 0], 1.0)  # one ulp of one number

    with pytest.raises(SchemaError, match="hash"):
        load_bank(_edited_copy(good, tmp_path / "edited.npz", nudge))
    with pytest.raises(SchemaError, match="version 99 is not supported"):
        load_bank(_edited_copy(good, tmp_path / "future.npz", lambda m: _header_version(m, 99)))
    with pytest.raises(SchemaError, match="not a table file"):
        load_bank(_edited_copy(good, tmp_path / "headless.npz", lambda m: m.pop("__header__")))
    with pytest.raises(ConfigError, match="not found"):
        load_bank(tmp_path / "missing.npz")
    with open(tmp_path / "array.npz", "wb") as f:
        np.save(f, np.zeros(3))  # a bare .npy under an .npz name
    with pytest.raises(SchemaError, match="not a table file"):
        load_bank(tmp_path / "array.npz")


def test_inconsistent_arrays_are_refused(bank):
    arrays = dict(bank.arrays)
    arrays["cell_interval"] = arrays["cell_interval"] + 10_000
    with pytest.raises(SchemaError, match="lookup cell"):
        TableBank(kind="table", detector_ids=bank.detector_ids, params=bank.params, domain=bank.domain,
                  options=bank.options, arrays=arrays)
    arrays = dict(bank.arrays)
    del arrays["coeffs"]
    with pytest.raises(SchemaError, match="expected"):
        TableBank(kind="table", detector_ids=bank.detector_ids, params=bank.params, domain=bank.domain,
                  options=bank.options, arrays=arrays)


# --- CLI ------------------------------------------------------------------------------------

def test_cli_build_and_info(tmp_path, params, capsys):
    pfile = tmp_path / "params.toml"
    dump_params(list(params.values()), pfile)
    out = tmp_path / "tables.npz"
    assert main(["tables", "build", "--params", str(pfile), "--out", str(out), "--quiet"]) == 0
    assert capsys.readouterr().out.startswith(f"wrote {out}: 4 detectors")  # -q: the last line stays
    assert main(["tables", "info", str(out), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    bank = load_bank(out)
    assert info["identity"] == bank.identity == build_bank(params).identity
    assert info["detectors"] == len(params) and info["kind"] == "table"
    gout = tmp_path / "grid.npz"
    assert main(["tables", "build", "--params", str(pfile), "--out", str(gout), "--kind", "grid",
                 "--n-power", "32", "--quiet"]) == 0
    assert load_bank(gout).kind == "grid"
    (tmp_path / "bad.npz").write_bytes(b"junk")
    assert main(["tables", "info", str(tmp_path / "bad.npz")]) == 2
    assert "not a readable table file" in capsys.readouterr().err


def test_bench_convert_smoke():
    import argparse

    from mntes_stream.bench import convert as bench

    parser = argparse.ArgumentParser()
    bench.add_arguments(parser)
    args = parser.parse_args(["--quick", "--detectors", "8", "--samples", "200", "--build-detectors", "4",
                              "--repeats", "1", "--no-numpy"])
    r = bench.run(args)
    for key in ("detectors", "samples", "msamples_per_s", "axpy_msamples_per_s", "ratio_to_axpy",
                "max_abs_error_w", "linear_max_abs_error_w", "build_s_per_1000_detectors",
                "bank_mib_per_5000_detectors"):
        assert key in r
    assert r["detectors"] == 8 and r["samples"] == 200
    assert r["max_abs_error_w"] <= 1e-19 < r["linear_max_abs_error_w"]
    low = r["low_responsivity"]  # the default's flags: those of the full sigma_P pass, the power untouched
    assert low["flags_identical_to_sigma_p_pass"] and low["power_identical_to_without"] and low["cost_ratio"] > 0
    assert r["flagged_samples"].get("low_responsivity", 0) == low["samples_flagged"]
    assert r["flags_identical_to_exact"]


def test_readme_example_runs(tmp_path, monkeypatch, capsys):
    """The Python example of docs/physics.md's "Response tables and conversion" section, as printed there."""
    from pathlib import Path

    text = (Path(__file__).resolve().parents[1] / "docs" / "physics.md").read_text()
    section = text[text.index("## Response tables and conversion"):]
    code = section[section.index("```python") + len("```python"):]
    code = code[: code.index("```")]
    monkeypatch.chdir(tmp_path)
    ns: dict = {}
    exec(compile(code, "docs/physics.md", "exec"), ns)
    printed = capsys.readouterr().out
    assert "0.29999" in printed and "0.69999" in printed
    assert (tmp_path / "tables.npz").exists()
    # What the page's comments say the example prints.
    assert np.all(ns["out"].flags == 0) and ns["out"].identity == ns["bank"].identity
    np.testing.assert_allclose((ns["lin"].p_opt_w - ns["out"].p_opt_w)[0] * 1e12, [-0.023, -0.044], atol=0.0015)

"""Parameter validation and parameter files."""

from __future__ import annotations

import dataclasses

import pytest

from mntes_stream.core.params import params_from_dict, table1_params
from mntes_stream.core.transition import ArctanTransition, TabulatedTransition
from mntes_stream.errors import ConfigError
from mntes_stream.io.paramfile import dump_params, load_params, parse_params


def test_table1_preset_round_trips_through_toml(tmp_path):
    dets = [table1_params("a"), table1_params("b", z_thev_ohm=0.02 - 0.03j, pickup_a_per_t=1e-3j)]
    tab = TabulatedTransition(t_k=(0.17, 0.175, 0.18, 0.185, 0.19), r_ohm=(0.0, 0.1, 0.5, 0.9, 1.0))
    dets.append(dets[0].replace(detector_id="c", transition=tab))
    path = tmp_path / "params.toml"
    dump_params(dets, path)
    back = load_params(path)
    assert list(back) == ["a", "b", "c"]
    assert back["b"] == dets[1]
    assert back["c"].transition.t_k == tab.t_k
    assert back["a"].to_dict() == dets[0].to_dict()


def test_defaults_preset_and_overrides():
    doc = {
        "schema": "mntes-params", "version": 1,
        "defaults": {"preset": "table1", "t_bath_k": 0.098},
        "detectors": {"x": {}, "y": {"t_c_k": 0.19, "z_thev_ohm": [0.01, 0.02]}},
    }
    d = parse_params(doc)
    assert d["x"].t_bath_k == 0.098 and d["x"].transition.t_c_k == 0.18
    assert d["y"].transition.t_c_k == 0.19 and d["y"].z_thev_ohm == complex(0.01, 0.02)


@pytest.mark.parametrize(
    "change, message",
    [
        ({"bogus_key": 1}, "unknown parameter"),
        ({"r_n_ohm": -1.0}, "r_n_ohm"),
        ({"t_bath_k": 0.2}, "below the transition"),
        ({"k_w_per_k_n": 0.0}, "k_w_per_k_n"),
        ({"n": float("nan")}, "n: expected a number > 1, got nan"),
        ({"t_c_k": "0.18"}, "t_c_k: expected a number .* got '0.18'"),  # a quoted number is named, not a traceback
        ({"v_thev_v": "8e-7"}, "v_thev_v: expected a number"),
        ({"z_thev_ohm": [-0.1, 0.0]}, "passive"),
        ({"transition": "vortex"}, "transition: expected one of 'arctan', 'tabulated'"),
        ({"current_shift_k_per_a": -1.0}, "current_shift"),
    ],
)
def test_unphysical_or_unknown_values_are_rejected(change, message):
    d = table1_params().to_dict()
    d.update(change)
    with pytest.raises(ConfigError, match=message):
        params_from_dict(d)


def test_missing_values_are_named():
    d = table1_params().to_dict()
    del d["k_w_per_k_n"]
    with pytest.raises(ConfigError, match="k_w_per_k_n"):
        params_from_dict(d)
    d = table1_params().to_dict()
    del d["iqr_k"]
    with pytest.raises(ConfigError, match="iqr_k"):
        params_from_dict(d)


def test_file_errors(tmp_path):
    with pytest.raises(ConfigError, match="not found"):
        load_params(tmp_path / "nope.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("schema = 'mntes-params'\nversion = 99\n[detectors.a]\n")
    with pytest.raises(ConfigError, match="version"):
        load_params(bad)
    bad.write_text("this is = = not toml")
    with pytest.raises(ConfigError, match="TOML"):
        load_params(bad)
    bad.write_text("schema = 'mntes-params'\nversion = 1\n[detectors.a]\npreset='table1'\nt_c_k = -3\n")
    with pytest.raises(ConfigError, match=r"detectors\.a"):
        load_params(bad)


def test_tabulated_transition_validation():
    with pytest.raises(ConfigError):
        TabulatedTransition(t_k=(0.1, 0.2), r_ohm=(0.0, 1.0))
    with pytest.raises(ConfigError, match="strictly increasing"):
        TabulatedTransition(t_k=(0.1, 0.2, 0.15, 0.3), r_ohm=(0.0, 0.3, 0.6, 1.0))
    with pytest.raises(ConfigError, match="non-decreasing"):
        TabulatedTransition(t_k=(0.1, 0.2, 0.25, 0.3), r_ohm=(0.0, 0.6, 0.3, 1.0))
    with pytest.raises(ConfigError):
        ArctanTransition(t_c_k=0.18, iqr_k=0.0, r_n_ohm=1.0)


def test_params_are_frozen():
    p = table1_params()
    with pytest.raises(dataclasses.FrozenInstanceError):
        p.n = 3.0  # type: ignore[misc]
    assert p.replace(n=3.0).n == 3.0 and p.n == 3.6

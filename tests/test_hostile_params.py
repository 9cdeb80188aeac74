"""Hostile or mistaken detector parameters: a one-line error naming the file, or a loud status, never a traceback.

Measured before issue 18: a non-numeric value ended in a traceback, a detector id such as ``../../x`` was
accepted, and parameters that matched no detector on the stream made every row NaN with an empty
``last_error``.
"""

from __future__ import annotations

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mntes_stream.core.ids import check_detector_id
from mntes_stream.errors import ConfigError
from mntes_stream.io.paramfile import load_params, parse_params

HEAD = {"schema": "mntes-params", "version": 1}


def _doc(**parts):
    return HEAD | parts


@pytest.mark.parametrize("doc,match", [
    (_doc(defaults={"preset": "table1"}, detectors={"b0m0c000": {"t_c_k": "abc"}}), "t_c_k: expected a number"),
    (_doc(defaults={"preset": "table1"}, detectors={"b0m0c000": {"z_thev_ohm": ["a", "b"]}}), "z_thev_ohm"),
    (_doc(defaults={"preset": "table1"}, detectors={"b0m0c000": {"n": True}}), "n: expected a number"),
    (_doc(defaults={"preset": "table1"}, detectors={"b0m0c000": {"transition_t_k": ["x"]}}), "transition_t_k"),
    (_doc(defaults={"preset": ["table1"]}, detectors={"b0m0c000": {}}), "unknown preset"),
    (_doc(defaults=3, detectors={"b0m0c000": {}}), r"\[defaults\] must be a table"),
    (_doc(defaults={"preset": "table1"}, detectors={"b0m0c000": 7}), "must be a table"),
    (_doc(defaults={"preset": "table1"}, detectors={"../../x": {}}), "'../../x' is not a safe name"),
    (_doc(defaults={"preset": "table1"}, detectors={"..": {}}), "not a safe name"),
    (_doc(defaults={"preset": "table1"}, detectors={"b0m0c000\n": {}}), "not a safe name"),
    (_doc(defaults={"preset": "table1"}, detectors={"a/b": {}}), "not a safe name"),
    (_doc(defaults={"preset": "table1"}, detectors={"x" * 129: {}}), "not a safe name"),
])
def test_bad_values_and_unsafe_ids_are_one_line_errors_naming_the_file(doc, match):
    with pytest.raises(ConfigError, match=match) as err:
        parse_params(doc, "p.toml")
    assert str(err.value).startswith("p.toml") and "\n" not in str(err.value)


_junk = st.one_of(st.text(max_size=5), st.booleans(), st.none(), st.floats(allow_nan=True, allow_infinity=True),
                  st.integers(min_value=-(10**30), max_value=10**30), st.lists(st.text(max_size=3), max_size=3),
                  st.dictionaries(st.text(max_size=3), st.integers(), max_size=2))
_keys = st.sampled_from(["t_c_k", "iqr_k", "r_n_ohm", "k_w_per_k_n", "n", "t_bath_k", "z_thev_ohm", "v_thev_v",
                         "gain_a_per_count", "transition", "transition_t_k", "transition_r_ohm", "preset", "detector_id"])


@settings(max_examples=300, deadline=None)
@given(changes=st.dictionaries(_keys, _junk, min_size=1, max_size=3), det_id=st.one_of(st.just("b0m0c000"), st.text(max_size=8)),
       where=st.sampled_from(["defaults", "detector"]))
def test_any_value_of_any_type_gives_params_or_a_config_error(changes, det_id, where):
    defaults = {"preset": "table1"} | (changes if where == "defaults" else {})
    doc = _doc(defaults=defaults, detectors={det_id: changes if where == "detector" else {}})
    try:
        out = parse_params(doc, "p.toml")
    except ConfigError as exc:
        assert "\n" not in str(exc)
        return
    (p,) = out.values()
    check_detector_id(p.detector_id)
    assert math.isfinite(p.v_thev_v) and math.isfinite(p.t_bath_k)


def test_a_binary_or_missing_file_is_a_config_error(tmp_path):
    f = tmp_path / "p.toml"
    f.write_bytes(b"\xff\xfe\x00binary")
    with pytest.raises(ConfigError, match="not a text"):
        load_params(f)
    with pytest.raises(ConfigError, match="not found"):
        load_params(tmp_path / "none.toml")

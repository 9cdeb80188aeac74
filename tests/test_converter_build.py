"""One builder: the converter service's config and a recording's provenance both give a ConverterSpec, and
build_converter makes the same converter of either, with one table cache and one snapshot."""

from __future__ import annotations

import dataclasses

import pytest

from mntes_stream.core.params import table1_params
from mntes_stream.errors import ConfigError
from mntes_stream.io.messages import Provenance
from mntes_stream.io.paramfile import dump_params, params_to_toml
from mntes_stream.pipeline.build import ConverterSpec, build_converter
from mntes_stream.pipeline.offline import converter_for, spec_for
from mntes_stream.service.converter import ConverterConfig


def _params():
    return [table1_params(f"b0m{m}c{c:03d}", r_n_ohm=1.0 + 0.01 * c) for m in range(2) for c in range(2)]


def test_the_service_and_a_recording_build_the_same_converter_through_one_cache(tmp_path):
    params = _params()
    dump_params(params, tmp_path / "p.toml")
    cache = tmp_path / "cache"
    live = ConverterConfig(params=str(tmp_path / "p.toml"), table_cache=str(cache), modules=(1,))
    spec = live.spec
    assert spec.params_file == str(tmp_path / "p.toml") and spec.modules == (1,) and spec.partial
    part = build_converter(spec)
    assert not part.from_snapshot and part.streams == [(0, 1)] and sorted(part.params) == ["b0m1c000", "b0m1c001"]
    assert sorted(part.converter.detector_ids) == sorted(part.params)

    prov = Provenance(setup="lab", params_toml=params_to_toml(params), table_identity="", converter_kind="table",
                      software_version="x", t_ns=0)
    offline = spec_for(prov, table_cache=cache)
    assert offline.params_toml == prov.params_toml and not offline.params_file and not offline.drop_untaken
    whole = build_converter(offline)
    assert whole.streams == [(0, 0), (0, 1)] and len(whole.converter.detector_ids) == 4
    # The same spec again: the converter as built, from its snapshot, converting with the same tables.
    again = build_converter(offline)
    assert again.from_snapshot and str(again.converter.identity) == str(whole.converter.identity)
    conv, pdict, psrc, tsrc = converter_for(prov, table_cache=cache)
    assert str(conv.identity) == str(whole.converter.identity) and psrc == "the recording's provenance"
    assert tsrc == "rebuilt from the parameters (table)" and list(pdict) == [p.detector_id for p in params]
    # One bank per set of detectors in the one cache: the service's part and the recording's whole plane.
    assert len(list(cache.glob("table-*.npz"))) == 2 and len(list(cache.glob("converter-table-*.pickle"))) == 2


def test_a_recording_with_other_tables_than_recorded_is_refused_in_one_line(tmp_path):
    params = _params()[:1]
    prov = Provenance(setup="lab", params_toml=params_to_toml(params), table_identity="f" * 64,
                      converter_kind="table", software_version="x", t_ns=0)
    with pytest.raises(ConfigError, match="the recording used ffffffff"):
        converter_for(prov, table_cache=None)
    with pytest.raises(ConfigError, match="no provenance with detector parameters"):
        spec_for(None)
    with pytest.raises(ConfigError, match="give the kind or the tables, not both"):
        spec_for(prov, tables="t.npz", kind="linear")


def test_a_spec_names_its_parameters_once_and_checks_what_it_says():
    with pytest.raises(ConfigError, match="names its parameters once, got params_file and params_toml"):
        ConverterSpec(params_file="p.toml", params_toml="schema = 1")
    with pytest.raises(ConfigError, match="needs its kind"):
        ConverterSpec(kind="", params_file="p.toml")
    with pytest.raises(ConfigError, match="gradients must be one of"):
        ConverterSpec(gradients="maybe")
    with pytest.raises(ConfigError, match="give detector parameters or a table bank file"):
        build_converter(ConverterSpec())
    spec = ConverterSpec(kind="exact", params=tuple((p.detector_id, p) for p in _params()))
    with pytest.raises(dataclasses.FrozenInstanceError):
        spec.kind = "table"  # type: ignore[misc]
    built = build_converter(spec)  # in memory (the G3 module): no snapshot, nothing to key it by
    assert not built.from_snapshot and built.converter.kind == "exact" and len(built.params) == 4

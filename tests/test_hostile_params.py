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
from mntes_stream.core.params import table1_params
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


def _pipeline_run(params, caplog):
    import numpy as np

    from mntes_stream.core.convert import make_converter
    from mntes_stream.io.messages import decode
    from mntes_stream.pipeline import ConverterPipeline, PipelineConfig
    from mntes_stream.service.source import MinimalSource, SourceConfig

    src = MinimalSource(SourceConfig(modules=2, channels=4, sample_rate_hz=200.0, chunk_s=0.1, hk_interval_s=0.1))
    pipe = ConverterPipeline(make_converter("exact", {p.detector_id: p for p in params}), PipelineConfig(), clock=None)
    start_error = pipe.last_error
    outs = []
    with caplog.at_level("WARNING", logger="mntes_stream.converter"):
        for t_pub, batch in src.batches(1_700_000_000_000_000_000, duration_s=1.0):
            for key, payload in batch:
                outs += pipe.handle(key, payload, t_pub)
        outs += pipe.flush()
    power = [decode(p) for k, p in outs if "/power/" in k]
    assert power and all(np.isnan(pw.p_opt_w).all() for pw in power)
    return pipe, start_error


def test_parameters_matching_no_channel_of_the_stream_say_so_once(caplog):
    # Module b0m0 and b0m1 are known, but the parameters are for channels 100-103: every row would be NaN.
    params = [table1_params(f"b0m{m}c{c:03d}") for m in (0, 1) for c in range(100, 104)]
    pipe, _ = _pipeline_run(params, caplog)
    st = pipe.status()
    assert st.last_error.startswith("no_detector on mntes/lab/counts/0/") and "UNKNOWN_CHANNEL" in st.last_error
    assert st.unknown_channel_samples > 0 and st.chunks_converted == 20
    said = [r.getMessage() for r in caplog.records if "no_detector" in r.getMessage()]
    assert len(said) == 2  # once per stream (channel list), not once per chunk


def test_detector_ids_that_are_names_are_said_at_start_and_match_only_named_rows(caplog):
    """Ids not of the form b<B>m<M>c<C> are names (counts chunks carrying detector_ids, e.g. the boards' names
    from dfmux-bridge): said at the start; any stream then gets state, and a stream none of whose rows has
    parameters is flagged UNKNOWN_CHANNEL, said once (never silently converted)."""
    import numpy as np

    from mntes_stream.core import flags as fl
    from mntes_stream.core.convert import make_converter
    from mntes_stream.io.messages import decode
    from mntes_stream.pipeline import ConverterPipeline, PipelineConfig
    from mntes_stream.service.source import MinimalSource, SourceConfig

    params = [table1_params("det-a"), table1_params("det-b"), table1_params("b0m1c000")]
    with caplog.at_level("INFO", logger="mntes_stream.converter"):
        pipe = ConverterPipeline(make_converter("exact", {p.detector_id: p for p in params}), PipelineConfig(),
                                 clock=None)
    assert sum("2 of 3 detector ids (e.g. 'det-a') are names" in r.getMessage() for r in caplog.records) == 1
    src = MinimalSource(SourceConfig(modules=2, channels=4, sample_rate_hz=200.0, chunk_s=0.1, hk_interval_s=0.1))
    outs = []
    for t_pub, batch in src.batches(1_700_000_000_000_000_000, duration_s=1.0):
        for key, payload in batch:
            outs += pipe.handle(key, payload, t_pub)
    outs += pipe.flush()
    st = pipe.status()
    assert not st.bad_messages.get("unknown_stream") and set(pipe._sequence.streams) == {(0, 0), (0, 1)}
    power = {}
    for k, p in outs:
        if "/power/" in k:
            pw = decode(p)
            power.setdefault(pw.module, []).append(pw)
    assert all(np.isnan(pw.p_opt_w).all() and np.all(pw.flags & fl.UNKNOWN_CHANNEL) for pw in power[0])
    assert sum("no_detector on mntes/lab/counts/0/0" in r.getMessage() for r in caplog.records) == 1


@pytest.mark.parametrize("detector,value,match", [
    ('"../../x"', "0.18", "detector id '../../x' is not a safe name"),
    ("b0m0c000", '"hot"', r"\[detectors.b0m0c000\] t_c_k: expected a number"),
    ("b0m0c000", "[0.1, 0.2]", r"t_c_k: expected a number"),
])
def test_serve_with_bad_parameters_ends_in_one_line_exit_2(tmp_path, detector, value, match):
    import re
    import subprocess
    import sys

    (tmp_path / "p.toml").write_text('schema = "mntes-params"\nversion = 1\n[defaults]\npreset = "table1"\n'
                                     f"[detectors.{detector}]\nt_c_k = {value}\n")
    (tmp_path / "c.toml").write_text('[converter]\nparams = "p.toml"\ntable_cache = ""\n')
    res = subprocess.run([sys.executable, "-m", "mntes_stream", "serve", "--config", "c.toml"], cwd=tmp_path,
                         capture_output=True, text=True, timeout=120)
    assert res.returncode == 2 and "Traceback" not in res.stderr
    (line,) = res.stderr.strip().splitlines()
    assert line.startswith("mntes-stream: error: ") and re.search(match, line) and "p.toml" in line

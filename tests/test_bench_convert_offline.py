"""Offline ``convert`` from the table cache (bank and converter snapshot), and ``bench convert-offline`` end to end."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys

import pytest

from mntes_stream.core.sim import SimConfig
from mntes_stream.io import keys
from mntes_stream.io.mcap import Session
from mntes_stream.io.messages import Provenance
from mntes_stream.io.paramfile import dump_params
from mntes_stream.pipeline.build import ConverterSpec, build_converter
from mntes_stream.pipeline.offline import convert_recording
from mntes_stream.service.simulator import SimulatorSource, write_mcap


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    work = tmp_path_factory.mktemp("offline-cache")
    source = SimulatorSource(SimConfig(boards=1, modules=2, channels=16), "bench", 0.1)
    dump_params(source.params, work / "params.toml")
    write_mcap(source, work / "rec.mcap", 2.0)
    return work


def _outputs(path):
    """Every message the conversion wrote, in order: (topic, log time, payload); a provenance decoded.

    A provenance carries when it was made (``t_ns``, wall clock): two conversions differ there and only there.
    """
    return [(m.topic, m.log_time_ns, dataclasses.replace(Provenance.from_bytes(m.payload), t_ns=0).to_bytes()
             if keys.kind_of(m.topic) == "provenance" else m.payload) for m in Session(path).iter_messages()]


def test_a_converter_from_the_cache_converts_bit_for_bit_as_one_built(recording):
    cache = recording / "cache"
    params = recording / "params.toml"
    built = convert_recording(recording / "rec.mcap", recording / "built.mcap", params=params, table_cache=None,
                              progress=False)
    cold = convert_recording(recording / "rec.mcap", recording / "cold.mcap", params=params, table_cache=cache,
                             progress=False)
    banks, snaps = list(cache.glob("table-*.npz")), list(cache.glob("converter-table-*.pickle"))
    assert len(banks) == 1 and len(snaps) == 1  # the cold run cached the bank and the converter as built
    warm = convert_recording(recording / "rec.mcap", recording / "warm.mcap", params=params, table_cache=cache,
                             progress=False)
    assert built.table_identity == cold.table_identity == warm.table_identity
    assert built.samples_converted == warm.samples_converted > 0 and warm.ledger_line == built.ledger_line
    reference = _outputs(recording / "built.mcap")
    assert sum(keys.kind_of(t) == "power" for t, _, _ in reference) == built.power_chunks > 0
    # Power, status, provenance: the same bytes at the same log times.
    assert _outputs(recording / "cold.mcap") == reference == _outputs(recording / "warm.mcap")
    # Other bytes are another key (a snapshot of its own), the same detectors the same bank.
    other = recording / "other.toml"
    other.write_text(params.read_text() + "\n# the same detectors\n")
    conv_other = build_converter(ConverterSpec(params_file=str(other), table_cache=str(cache))).converter
    assert len(list(cache.glob("converter-table-*.pickle"))) == 2
    assert str(conv_other.identity) == warm.table_identity  # same detectors, same tables: the same bank


def test_bench_convert_offline_on_a_small_recording():
    res = subprocess.run([sys.executable, "-m", "mntes_stream", "bench", "convert-offline", "--detectors", "32",
                          "--channels", "16", "--seconds", "2", "--repeat", "1", "--profile", "5", "--json"],
                         capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr
    out = json.loads(res.stdout)
    assert out["samples_converted"] == out["samples"] > 32 * 2 * 150 and "lost 0" in out["ledger"]
    assert out["realtime_factor"] == pytest.approx(2 / out["in_process_warm_s"][0], rel=0.05)
    assert out["realtime_factor_command"] == pytest.approx(2 / out["command_warm_s"][0], rel=0.05)
    # The warm command did not build what the cold one cached.
    assert out["command_warm_cpu_s"][0] < out["command_cold_cpu_s"]
    assert len(out["profile_top_own_time"]) == 5 and all(r["own_s"] >= 0 for r in out["profile_top_own_time"])
    assert set(out["parts_s"]) == {"converter_from_warm_cache", "read_recording", "decode_counts", "kernel"}
    assert out["batch_s"] == 0.0 and out["realtime_factor_at_batch_s_per_cpu_s"] > 0  # message by message
    assert out["command_startup_cpu_s"] is None  # --startup not given: one process fewer


def test_batched_offline_conversion_gives_the_same_power_and_flags(recording):
    """batch_s > 0 (the default: 1) puts each batch through handle_many: power and flags bit for bit as message by
    message (batch_s=0), stamps at batch ends; the output in lz4 chunks."""
    from mcap.reader import make_reader

    from mntes_stream.io.messages import PowerChunk

    def power(path):
        out = {}
        for m in Session(path).iter_messages():
            if keys.kind_of(m.topic) == "power":
                c = PowerChunk.from_bytes(m.payload)
                out[(c.board, c.module, c.seq)] = (c.p_opt_w.tobytes(), c.flags.tobytes(), m.log_time_ns)
        return out

    params = recording / "params.toml"
    one = convert_recording(recording / "rec.mcap", recording / "one.mcap", params=params, progress=False,
                            table_cache=recording / "cache", batch_s=0)
    many = convert_recording(recording / "rec.mcap", recording / "many.mcap", params=params, progress=False,
                             table_cache=recording / "cache")
    with open(recording / "many.mcap", "rb") as f:
        assert {c.compression for c in make_reader(f).get_summary().chunk_indexes} == {"lz4"}
    a, b = power(recording / "one.mcap"), power(recording / "many.mcap")
    assert set(a) == set(b) and len(a) == one.power_chunks == many.power_chunks > 0
    assert all(a[k][:2] == b[k][:2] for k in a)  # the same numbers
    assert all(b[k][2] >= a[k][2] for k in a) and any(b[k][2] > a[k][2] for k in a)  # stamped at the batch's end
    assert many.ledger_line == one.ledger_line and many.input_messages == one.input_messages
    with pytest.raises(Exception, match="batch_s must be >= 0"):
        convert_recording(recording / "rec.mcap", recording / "bad.mcap", params=params, batch_s=-1, progress=False)

"""Record -> replay -> re-record over real zenoh on 127.0.0.1; offline conversion."""

from __future__ import annotations

import json
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from mcap_helpers import (
    counts_payload,
    hk_payload,
    matched_publishers,
    provenance_payload,
    readable_messages,
    running_recorder,
)

from mntes_stream.errors import ConfigError
from mntes_stream.io import mcap as mio
from mntes_stream.io.transport import Publishers, ZenohSettings, open_session
from mntes_stream.service.replay import ReplayConfig, ReplayService, parse_time, run_replay


def _wait_count(directory, n, timeout_s=20.0):
    deadline = time.monotonic() + timeout_s
    while len(readable_messages(directory)) < n:
        if time.monotonic() > deadline:
            raise TimeoutError(f"{directory}: fewer than {n} messages recorded")
        time.sleep(0.05)


@pytest.fixture(scope="module")
def session_a(tmp_path_factory):
    """A live recording: counts on two modules, housekeeping, power-like and provenance traffic."""
    directory = tmp_path_factory.mktemp("a")
    plan = [("mntes/t/provenance", provenance_payload("a"))]
    for i in range(80):
        plan.append((f"mntes/t/counts/0/{i % 2}", counts_payload(i // 2, module=i % 2)))
        if i % 4 == 0:
            plan.append(("mntes/t/hk/t_bath", hk_payload(i // 4)))
        if i % 8 == 0:
            plan.append(("mntes/t/power/0/0", counts_payload(1000 + i)))  # stands in for an output
    with running_recorder(directory) as (ep, _):
        with open_session(ZenohSettings(connect=(ep,))) as z:
            pubs = matched_publishers(z, sorted({k for k, _ in plan}))
            for key, payload in plan:
                pubs.put(key, payload)
                time.sleep(0.004)  # ~0.5 s of traffic, so pacing is measurable
            _wait_count(directory, len(plan))
    return directory, list(mio.iter_messages(directory))


def _replay_into(tmp_path, source, **kw):
    with running_recorder(tmp_path) as (ep, out):
        cfg = ReplayConfig(source=(str(source),), zenoh=ZenohSettings(connect=(ep,)), wait_subscribers_s=30.0, linger_s=0.2, **kw)
        stats = run_replay(cfg)
        _wait_count(tmp_path, stats.messages)
    return stats, list(mio.iter_messages(tmp_path)), out["stats"]


def test_replay_inputs_as_fast_as_possible_rerecords_identically(session_a, tmp_path):
    src, recorded = session_a
    stats, again, rec = _replay_into(tmp_path, src, speed=0)
    inputs = [m for m in recorded if "/counts/" in m.topic or "/hk/" in m.topic]
    assert stats.messages == len(inputs) == 100 and not stats.unmatched_topics
    assert [(m.topic, m.payload) for m in again] == [(m.topic, m.payload) for m in inputs]
    assert rec.seq_gaps == 0 and rec.by_kind == {"counts": 80, "hk": 20}


def test_replay_everything_at_double_speed_keeps_pace(session_a, tmp_path, monkeypatch):
    src, recorded = session_a
    # The replay's own pacing: when its schedule starts (setup's last act, once subscribers match, is reading the
    # clock it schedules from) and when it hands each message to zenoh (puts from this thread; the recorder's run
    # in its own). The re-recording's log times are the recorder's receive times: a late first receipt (recorder
    # or zenoh busy) shortens their span even when the replay kept its schedule, so they do not measure its pace.
    replay_thread, begun, puts = threading.get_ident(), [], []
    setup, put = ReplayService.setup, Publishers.put

    def timed_setup(self, ctx):
        setup(self, ctx)
        begun.append(time.monotonic())

    def timed_put(self, key, payload):
        if threading.get_ident() == replay_thread:
            puts.append((time.monotonic(), key, payload))
        put(self, key, payload)

    monkeypatch.setattr(ReplayService, "setup", timed_setup)
    monkeypatch.setattr(Publishers, "put", timed_put)
    stats, again, _ = _replay_into(tmp_path, src, speed=2.0, topics=("**",))
    assert [(m.topic, m.payload) for m in again] == [(m.topic, m.payload) for m in recorded]
    assert [(k, p) for _, k, p in puts] == [(m.topic, m.payload) for m in recorded]
    span_a = (recorded[-1].log_time_ns - recorded[0].log_time_ns) / 1e9
    assert span_a > 0.3
    # Never ahead of the recorded schedule divided by the speed: message i goes out no earlier than its recorded
    # offset / 2 after the schedule began (5 ms: the instants between the replay's clock reading and ours).
    # A replay 2x too fast is ~0.12 s early by its last message, one as fast as possible ~0.23 s.
    early = [(m.log_time_ns - recorded[0].log_time_ns) / 1e9 / 2 - (t - begun[0]) for (t, _, _), m in zip(puts, recorded)]
    assert max(early) <= 0.005, f"a message went out {max(early):.3f} s ahead of the schedule"
    assert stats.recorded_span_s == pytest.approx(span_a, abs=1e-9)
    assert mio.latest_provenance(tmp_path) == provenance_payload("a")


def test_replay_cli_time_range(session_a, tmp_path):
    src, recorded = session_a
    t0 = recorded[0].log_time_ns
    lo, hi = parse_time("0.1", t0), parse_time("0.3", t0)
    expected = [m for m in recorded if lo <= m.log_time_ns < hi and "/counts/" in m.topic]
    assert expected
    with running_recorder(tmp_path) as (ep, _):
        out = subprocess.run(
            [sys.executable, "-m", "mntes_stream", "replay", str(src), "--afap", "--start", "0.1", "--end", "0.3",
             "--topics", "mntes/t/counts/**", "--connect", ep, "--wait-s", "30", "--json", "-q"],
            capture_output=True, text=True, timeout=60,
        )
        assert out.returncode == 0, out.stderr
        assert json.loads(out.stdout)["messages"] == len(expected)
        _wait_count(tmp_path, len(expected))
    assert [m.payload for m in mio.iter_messages(tmp_path)] == [m.payload for m in expected]


def test_parse_time_and_config_errors():
    assert parse_time("1.5", 10) == 10 + 1_500_000_000
    assert parse_time("2024-01-01T00:00:00Z", None) == 1_704_067_200_000_000_000
    with pytest.raises(ConfigError):
        parse_time("yesterday", 0)
    with pytest.raises(ConfigError):
        ReplayConfig(speed=-1)
    from mntes_stream.service.config import load_service_config

    _, cfg = load_service_config("services/replay.toml", ["replay.source=['x.mcap']"])
    assert cfg.topics == () and cfg.source == (str(Path("x.mcap").resolve()),) and cfg.speed == 1.0  # (): the inputs
    _, cfg = load_service_config("services/replay.toml")  # its source: what services/recorder.toml records
    assert cfg.source == (str(Path("services/recordings").resolve()),)


@pytest.mark.parametrize("line, match", [
    ('speed = "2"', "speed: expected a number >= 0, got '2'"),
    ("speed = nan", "speed: expected a number"),
    ("linger_s = inf", "linger_s: expected a number"),
    ("wait_subscribers_s = -1", r"wait_subscribers_s: expected a number \(s\) >= 0"),
    ('topics = "mntes/**"', "topics: expected a list of strings"),
    ('source = ["a.mcap", 3]', "source: expected a list of strings"),
    ("start_ns = 1.5", "start_ns: expected an integer"),
    ("start_ns = 10\nend_ns = 5", "end must be after start"),
    ("speeed = 1", "unknown key"),
])
def test_replay_config_errors_name_the_value(tmp_path, line, match):
    from mntes_stream.service.config import load_service_config

    bad = tmp_path / "bad.toml"
    bad.write_text(f"[replay]\n{line}\n")
    with pytest.raises(ConfigError, match=match):
        load_service_config(bad)


def test_replay_default_selects_the_inputs_of_every_setup(tmp_path):
    from mntes_stream.io.transport import free_tcp_port, loopback

    path = tmp_path / "two.mcap"
    with mio.McapFileWriter(path) as w:
        for i, key in enumerate(["mntes/a/counts/0/0", "mntes/b/hk/t_bath", "mntes/a/power/0/0", "mntes/a/provenance",
                                 "mntes/b/status/converter", "other/a/counts/0/0"]):
            w.write(key, counts_payload(i), T0 + i)
    stats = run_replay(ReplayConfig(source=(str(path),), speed=0, wait_subscribers_s=0, linger_s=0, zenoh=loopback(free_tcp_port())))
    assert stats.topics == 2 and stats.messages == 2 and stats.by_kind == {"counts": 1, "hk": 1}


# ---------------------------------------------------------------------------- offline conversion

T0 = 1_700_000_000_000_000_000


@pytest.fixture(scope="module")
def source_recording(tmp_path_factory):
    """A recording of the minimal source plus what a converter pipeline made of it.

    Written directly (no zenoh): log time = publication time + 1 ms, the
    pipeline's outputs stamped and logged at that time, as the recorder would.
    """
    from mntes_stream.core.convert import make_converter
    from mntes_stream.io import keys
    from mntes_stream.pipeline import ConverterPipeline, PipelineConfig
    from mntes_stream.service.source import MinimalSource, SourceConfig

    src = MinimalSource(SourceConfig(setup="t", modules=2, channels=8))
    params = {p.detector_id: p for p in src.params}
    pipe = ConverterPipeline(make_converter("table", params), PipelineConfig(setup="t"), params=params, clock=None)
    path = tmp_path_factory.mktemp("src") / "in.mcap"
    with mio.McapFileWriter(path) as w:
        w.write(keys.provenance_key("t"), pipe.provenance_bytes(), T0)
        for t_pub, batch in src.batches(T0, 3.0):
            t_log = t_pub + 1_000_000
            for key, payload in batch:
                w.write(key, payload, t_log)
                for k2, p2 in pipe.handle(key, payload, t_log):
                    w.write(k2, p2, t_log)
        for k2, p2 in pipe.flush():
            w.write(k2, p2, t_log)
    return path, src


def _power(source):
    from mntes_stream.io.messages import PowerChunk

    return [PowerChunk.from_bytes(m.payload) for m in mio.iter_messages(source, topics="mntes/*/power/**")]


def test_offline_convert_reproduces_the_recorded_conversion(source_recording, tmp_path):
    import numpy as np

    from mntes_stream.pipeline.offline import convert_recording

    path, src = source_recording
    out = tmp_path / "out.mcap"
    stats = convert_recording(path, out, progress=False)
    rec, new = _power(path), _power(out)
    assert len(new) == len(rec) == stats.power_chunks == mio.Session(path).count("mntes/t/counts/**") > 50
    for a, b in zip(rec, new):
        assert (a.board, a.module, a.seq, a.t0_ns) == (b.board, b.module, b.seq, b.t0_ns)
        assert np.array_equal(a.p_opt_w, b.p_opt_w, equal_nan=True) and np.array_equal(a.flags, b.flags)
    assert stats.table_identity == stats.recorded_table_identity and stats.bad_messages == {}
    # Physics: against the source's optical-power truth. Counts are integer-rounded, and the
    # linearly interpolated housekeeping misses the triangle waves' corners by a little, hence
    # a sharp median and a looser maximum (6e-4 of the 0.5 pW loading).
    err = np.concatenate([np.abs(b.p_opt_w - src.truth_p_opt_w(b.board, b.module, b.times_ns(), T0)).ravel() for b in new])
    assert np.median(err) < 1e-18 and err.max() < 5e-16 and not any(b.flags.any() for b in new)
    # The output holds the inputs verbatim and explains itself like a recording.
    inputs = [m.payload for m in mio.iter_messages(path, topics=["mntes/t/counts/**", "mntes/t/hk/**"])]
    assert [m.payload for m in mio.iter_messages(out, topics=["mntes/t/counts/**", "mntes/t/hk/**"])] == inputs
    meta = {m.name: m.data for m in mio.read_metadata(out)}
    assert meta["mntes.recording"]["mode"] == "offline conversion"
    # Deterministic: a second conversion emits the same power and status bytes.
    convert_recording(path, tmp_path / "again.mcap", progress=False)
    outputs = ["mntes/t/power/**", "mntes/t/status/**"]
    assert [m.payload for m in mio.iter_messages(tmp_path / "again.mcap", topics=outputs)] == \
        [m.payload for m in mio.iter_messages(out, topics=outputs)]
    assert meta["mntes.provenance"]["table_identity"] == stats.table_identity


def test_offline_convert_with_new_parameters_via_cli(source_recording, tmp_path):
    import numpy as np

    from mntes_stream.io.paramfile import dump_params

    path, src = source_recording
    newer = [p.replace(t_c_k=p.transition.t_c_k * 1.001) for p in src.params]  # a "newer calibration"
    dump_params(newer, tmp_path / "newer.toml")
    out = tmp_path / "out.mcap"
    res = subprocess.run([sys.executable, "-m", "mntes_stream", "convert", str(path), str(out),
                          "--params", str(tmp_path / "newer.toml"), "--json", "-q"], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    stats = json.loads(res.stdout)
    assert stats["params_source"].endswith("newer.toml") and stats["table_identity"] != stats["recorded_table_identity"]
    rec, new = _power(path), _power(out)
    assert len(new) == len(rec)
    # A higher T_c means a higher TES temperature at the same resistance, so more total power
    # K (T^n - T_bath^n): the new parameters infer more optical power from the same counts.
    shift = np.mean([np.nanmean(b.p_opt_w - a.p_opt_w) for a, b in zip(rec, new)])
    assert shift > 1e-15
    # Running it again is a refusal, not an overwrite (one line naming the flag that would).
    res = subprocess.run([sys.executable, "-m", "mntes_stream", "convert", str(path), str(out), "-q"],
                         capture_output=True, text=True, timeout=120)
    assert res.returncode == 2 and "exists (--overwrite replaces it)" in res.stderr
    assert len(res.stderr.strip().splitlines()) == 1


def test_offline_convert_with_a_table_file(source_recording, tmp_path):
    """--tables: a bank built elsewhere (newer calibration) gives the same power as rebuilding from --params."""
    import numpy as np

    from mntes_stream.core.tables import build_bank
    from mntes_stream.io.paramfile import dump_params
    from mntes_stream.io.tablefile import save_bank
    from mntes_stream.pipeline.offline import convert_recording

    path, src = source_recording
    newer = [p.replace(t_c_k=p.transition.t_c_k * 1.001) for p in src.params]
    bank = build_bank({p.detector_id: p for p in newer})
    save_bank(bank, tmp_path / "newer.npz")
    dump_params(newer, tmp_path / "newer.toml")
    by_tables = convert_recording(path, tmp_path / "t.mcap", tables=tmp_path / "newer.npz", progress=False)
    by_params = convert_recording(path, tmp_path / "p.mcap", params=tmp_path / "newer.toml", progress=False)
    assert by_tables.table_identity == bank.identity == by_params.table_identity != by_tables.recorded_table_identity
    assert by_tables.tables_source.endswith("newer.npz")
    for a, b in zip(_power(tmp_path / "t.mcap"), _power(tmp_path / "p.mcap"), strict=True):
        assert np.array_equal(a.p_opt_w, b.p_opt_w) and np.array_equal(a.flags, b.flags)
    assert mio.latest_provenance(tmp_path / "t.mcap") is not None  # the output records what it used
    meta = [m.data for m in mio.read_metadata(tmp_path / "t.mcap") if m.name == "mntes.provenance"]
    assert meta[-1]["table_identity"] == bank.identity


def test_offline_convert_needs_parameters(tmp_path):
    from mntes_stream.pipeline.offline import convert_recording

    path = tmp_path / "bare.mcap"
    with mio.McapFileWriter(path) as w:
        w.write("mntes/t/counts/0/0", counts_payload(0), T0)
    with pytest.raises(ConfigError, match="no provenance"):
        convert_recording(path, tmp_path / "out.mcap", progress=False)


@pytest.fixture(scope="module")
def two_calibrations(tmp_path_factory):
    """A rotated recording whose converter was restarted half way with other parameters (T_c 0.1 % higher).

    Written directly, as the live services would have: calibration A (the source's truth)
    until ``t_switch``; there the old converter converts what it holds and stops, the new
    one publishes its provenance and converts from then on. Rotation repeats provenance.
    """
    from mntes_stream.core.convert import make_converter
    from mntes_stream.io import keys
    from mntes_stream.io.paramfile import dump_params
    from mntes_stream.pipeline import ConverterPipeline, PipelineConfig
    from mntes_stream.service.source import MinimalSource, SourceConfig

    src = MinimalSource(SourceConfig(setup="t", modules=1, channels=4))
    calib = {"a": src.params, "b": [p.replace(t_c_k=p.transition.t_c_k * 1.001) for p in src.params]}
    convs = {k: make_converter("table", {p.detector_id: p for p in v}) for k, v in calib.items()}
    directory = tmp_path_factory.mktemp("two")
    dump_params(calib["b"], directory.parent / "b.toml")
    t_switch = T0 + 1_500_000_000
    w = mio.RotatingMcapWriter(directory, "c", rotate_bytes=60_000, rotate_s=0)
    prov_key = keys.provenance_key("t")

    def pipeline(k):
        return ConverterPipeline(convs[k], PipelineConfig(setup="t"), params=calib[k], clock=None)

    pipe = pipeline("a")
    w.write(prov_key, pipe.provenance_bytes(), T0)
    for t_pub, batch in src.batches(T0, 3.0):
        t_log = t_pub + 1_000_000
        if t_log >= t_switch and pipe.converter is convs["a"]:
            for k2, p2 in pipe.tick(t_switch) + pipe.flush():
                w.write(k2, p2, t_switch)
            pipe = pipeline("b")
            w.write(prov_key, pipe.provenance_bytes(), t_switch)
        for key, payload in batch:
            w.write(key, payload, t_log)
            for k2, p2 in pipe.handle(key, payload, t_log):
                w.write(k2, p2, t_log)
        w.write(prov_key, pipe.provenance_bytes(), t_log)  # republished: no new calibration
    for k2, p2 in pipe.flush():
        w.write(k2, p2, t_log)
    w.close()
    assert len(w.files) >= 3
    return directory, src, {k: str(c.identity) for k, c in convs.items()}, t_switch


def test_offline_convert_switches_calibration_where_the_recording_did(two_calibrations, tmp_path):
    import numpy as np

    from mntes_stream.pipeline.offline import convert_recording, recorded_calibrations

    directory, src, ident, t_switch = two_calibrations
    assert [(t, p.table_identity) for t, p in recorded_calibrations(mio.Session(directory))] == \
        [(T0, ident["a"]), (t_switch, ident["b"])]  # repeats and rotated copies are one calibration each
    stats = convert_recording(directory, tmp_path / "out.mcap", progress=False)
    assert stats.calibrations == 2 and stats.table_identity == stats.recorded_table_identity == ident["b"]
    assert "changed 1 time(s)" in stats.summary()
    rec, new = _power(directory), _power(tmp_path / "out.mcap")
    assert len(new) == len(rec) == mio.Session(directory).count("mntes/t/counts/**")
    for a, b in zip(rec, new, strict=True):
        assert (a.seq, a.table_identity) == (b.seq, b.table_identity)
        assert np.array_equal(a.p_opt_w, b.p_opt_w, equal_nan=True) and np.array_equal(a.flags, b.flags)
    # Independently of the recorded power: the part before the switch, converted with the truth,
    # gives the source's optical power; the part after carries the newer calibration's bias.
    before = [b for b in new if b.table_identity == ident["a"]]
    after = [b for b in new if b.table_identity == ident["b"]]
    assert before and after and max(b.t0_ns for b in before) < min(b.t0_ns for b in after) < t_switch
    err = [b.p_opt_w - src.truth_p_opt_w(b.board, b.module, b.times_ns(), T0) for b in before]
    assert max(np.nanmax(np.abs(e)) for e in err) < 5e-16
    assert np.mean([np.nanmean(b.p_opt_w - src.truth_p_opt_w(b.board, b.module, b.times_ns(), T0)) for b in after]) > 1e-15


def test_offline_convert_override_of_several_calibrations_warns(two_calibrations, tmp_path, caplog):
    from mntes_stream.pipeline.offline import convert_recording

    directory, src, ident, _ = two_calibrations
    with caplog.at_level("WARNING", logger="mntes_stream.offline"):
        stats = convert_recording(directory, tmp_path / "out.mcap", params=directory.parent / "b.toml", progress=False)
    assert "holds 2 calibrations" in caplog.text and "replace all of them" in caplog.text
    assert stats.calibrations == 1 and {p.table_identity for p in _power(tmp_path / "out.mcap")} == {ident["b"]}


def _live_run(tmp_path, name, params_file, feed, n_power):
    """A live converter and a recorder of its inputs and outputs; ``feed(zenoh settings)`` publishes the inputs.

    Returns the recording directory once ``n_power`` power chunks are in it and
    both services have stopped (converter first, so it converts what it holds).
    """
    from mntes_stream.io.transport import free_tcp_port
    from mntes_stream.pipeline import PipelineConfig
    from mntes_stream.service.converter import ConverterConfig, run_converter

    rec_dir = tmp_path / name
    with running_recorder(rec_dir) as (ep_rec, _):
        ep_conv = f"tcp/127.0.0.1:{free_tcp_port()}"
        conv_cfg = ConverterConfig.for_pipeline(PipelineConfig(setup="t"), params=str(params_file), kind="table",
                                   zenoh=ZenohSettings(listen=(ep_conv,), connect=(ep_rec,)))
        stop, ready = threading.Event(), threading.Event()
        conv = threading.Thread(target=run_converter, args=(conv_cfg, stop, ready))
        conv.start()
        try:
            while not ready.wait(0.05):
                assert conv.is_alive(), "the converter failed to start"
            feed(ZenohSettings(connect=(ep_conv, ep_rec)))
            deadline = time.monotonic() + 30
            while time.monotonic() < deadline:
                if sum(m.topic.startswith("mntes/t/power/") for m in readable_messages(rec_dir)) >= n_power:
                    break
                time.sleep(0.1)
        finally:
            stop.set()
            conv.join(30)
    return rec_dir


def test_live_replayed_and_offline_conversions_agree(tmp_path):
    """source -> live converter -> recorder; replay of that recording -> live converter -> recorder;
    offline conversion of the first recording: the same power and flags, sample for sample."""
    import numpy as np

    from mntes_stream.io import keys
    from mntes_stream.io.paramfile import dump_params
    from mntes_stream.pipeline.offline import convert_recording
    from mntes_stream.service.source import MinimalSource, SourceConfig, publish

    src = MinimalSource(SourceConfig(setup="t", modules=2, channels=4, sample_rate_hz=200.0, chunk_s=0.1, hk_interval_s=0.1))
    params_file = tmp_path / "params.toml"
    dump_params(src.params, params_file)
    n_power = 2 * 20  # 2 s of 0.1 s chunks on two modules

    def from_source(z_settings):
        with open_session(z_settings) as z:
            wait = [keys.counts_key("t", 0, m) for m in range(2)] + [keys.hk_key("t", s) for s in ("t_bath", "b_field")]
            assert publish(z, src.batches(time.time_ns(), 2.0), speed=0, wait_keys=wait, wait_s=30)["matched"]

    live_dir = _live_run(tmp_path, "live", params_file, from_source, n_power)

    def from_recording(z_settings):
        stats = run_replay(ReplayConfig(source=(str(live_dir),), speed=0, zenoh=z_settings, wait_subscribers_s=30))
        assert stats.messages == 2 * 20 + 2 * 20 and not stats.unmatched_topics  # counts + hk (t_bath, b_field)

    replay_dir = _live_run(tmp_path, "replayed", params_file, from_recording, n_power)
    stats = convert_recording(live_dir, tmp_path / "offline.mcap", progress=False)
    assert stats.table_identity == stats.recorded_table_identity
    runs = [{(p.module, p.seq): p for p in _power(d)} for d in (live_dir, replay_dir, tmp_path / "offline.mcap")]
    live = runs[0]
    assert len(live) == n_power and all(np.isfinite(p.p_opt_w).all() for p in live.values())
    for other in runs[1:]:
        assert other.keys() == live.keys()
        for k, a in live.items():
            b = other[k]
            assert np.array_equal(a.p_opt_w, b.p_opt_w) and np.array_equal(a.flags, b.flags), k


def test_replay_without_subscribers_says_so(session_a):
    from mntes_stream.io.transport import free_tcp_port, loopback

    src, recorded = session_a
    cfg = ReplayConfig(source=(str(src),), speed=0, topics=("mntes/t/hk/**",), wait_subscribers_s=0.2, linger_s=0,
                       zenoh=loopback(free_tcp_port()))
    stats = run_replay(cfg)
    assert stats.unmatched_topics == ("mntes/t/hk/t_bath",) and stats.messages == 20

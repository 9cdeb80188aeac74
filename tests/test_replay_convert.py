"""Record -> replay -> re-record over real zenoh on 127.0.0.1; offline conversion."""

from __future__ import annotations

import json
import subprocess
import sys
import threading
import time
import warnings
from contextlib import contextmanager

import pytest
import zenoh
from mcap_helpers import counts_payload, free_endpoint, hk_payload, provenance_payload, wait_matching

from mntes_stream.errors import ConfigError
from mntes_stream.io import mcap_io as mio
from mntes_stream.io.transport import ZenohSettings, open_session
from mntes_stream.service.recorder import RecorderConfig, run_recorder
from mntes_stream.service.replay import ReplayConfig, parse_time, run_replay


@contextmanager
def recording(directory, ep):
    """A recorder of mntes/t/** listening on ``ep`` for the duration of the block."""
    cfg = RecorderConfig(setup="t", directory=str(directory), flush_interval_s=0.1, zenoh=ZenohSettings(listen=(ep,)))
    stop = threading.Event()
    out = {}
    th = threading.Thread(target=lambda: out.update(stats=run_recorder(cfg, stop)))
    th.start()
    try:
        yield out
    finally:
        stop.set()
        th.join(30)


def _readable(directory):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", mio.TruncatedFileWarning)
        try:
            return list(mio.iter_messages(directory))
        except Exception:
            return []


def _wait_count(directory, n, timeout_s=20.0):
    deadline = time.monotonic() + timeout_s
    while len(_readable(directory)) < n:
        if time.monotonic() > deadline:
            raise TimeoutError(f"{directory}: fewer than {n} messages recorded")
        time.sleep(0.05)


@pytest.fixture(scope="module")
def session_a(tmp_path_factory):
    """A live recording: counts on two modules, housekeeping, power-like and provenance traffic."""
    directory = tmp_path_factory.mktemp("a")
    ep = free_endpoint()
    plan = [("mntes/t/provenance", provenance_payload("a"))]
    for i in range(80):
        plan.append((f"mntes/t/counts/0/{i % 2}", counts_payload(i // 2, module=i % 2)))
        if i % 4 == 0:
            plan.append(("mntes/t/hk/t_bath", hk_payload(i // 4)))
        if i % 8 == 0:
            plan.append(("mntes/t/power/0/0", counts_payload(1000 + i)))  # stands in for an output
    with recording(directory, ep):
        with open_session(ZenohSettings(connect=(ep,))) as z:
            pubs = {k: z.declare_publisher(k, congestion_control=zenoh.CongestionControl.BLOCK) for k, _ in plan}
            for p in pubs.values():
                wait_matching(p, 30.0)
            for key, payload in plan:
                pubs[key].put(payload)
                time.sleep(0.004)  # ~0.5 s of traffic, so pacing is measurable
            _wait_count(directory, len(plan))
    return directory, list(mio.iter_messages(directory))


def _replay_into(tmp_path, source, **kw):
    ep = free_endpoint()
    with recording(tmp_path, ep) as out:
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


def test_replay_everything_at_double_speed_keeps_pace(session_a, tmp_path):
    src, recorded = session_a
    stats, again, _ = _replay_into(tmp_path, src, speed=2.0, topics=("**",))
    assert [(m.topic, m.payload) for m in again] == [(m.topic, m.payload) for m in recorded]
    span_a = (recorded[-1].log_time_ns - recorded[0].log_time_ns) / 1e9
    span_b = (again[-1].log_time_ns - again[0].log_time_ns) / 1e9
    assert span_a > 0.3
    # Never ahead of the recorded schedule divided by the speed.
    assert span_b >= 0.95 * span_a / 2
    assert stats.recorded_span_s == pytest.approx(span_a, abs=1e-9)
    assert mio.latest_provenance(tmp_path) == provenance_payload("a")


def test_replay_cli_time_range(session_a, tmp_path):
    src, recorded = session_a
    t0 = recorded[0].log_time_ns
    lo, hi = parse_time("0.1", t0), parse_time("0.3", t0)
    expected = [m for m in recorded if lo <= m.log_time_ns < hi and "/counts/" in m.topic]
    assert expected
    ep = free_endpoint()
    with recording(tmp_path, ep):
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
    cfg = ReplayConfig.from_toml("services/replay.toml", source=("x.mcap",))
    assert cfg.topics == ("mntes/*/counts/**", "mntes/*/hk/**") and cfg.source == ("x.mcap",)

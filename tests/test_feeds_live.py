"""Live power feed over real zenoh on 127.0.0.1: what a publisher sends is what the iterator yields."""

from __future__ import annotations

import re
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from test_feeds import RATE, STEP, T0, N, bits, chunk, write

from mntes_stream.core import flags as fl
from mntes_stream.errors import ConfigError
from mntes_stream.feeds import LivePowerFeed
from mntes_stream.io import keys
from mntes_stream.io.mcap import RotatingMcapWriter
from mntes_stream.io.transport import Publishers, free_tcp_port, loopback, open_session


class _Publisher(threading.Thread):
    """Publishes ``plan`` once the feed subscribed; keeps its session open until told (no loss at close).

    Connects to the feed's ``port``, or (``listen=True``) listens on it for the feed to connect.
    """

    def __init__(self, port: int, plan: list[tuple[str, bytes]], wait_keys, listen: bool = False):
        super().__init__(daemon=True)
        self.port, self.plan, self.wait_keys = port, plan, list(wait_keys)
        self.settings = loopback(listen_port=port) if listen else loopback(connect_ports=[port])
        self.ready = threading.Event()  # the session is open
        self.done = threading.Event()
        self.error: BaseException | None = None

    def run(self) -> None:
        try:
            with open_session(self.settings) as z:
                self.ready.set()
                pubs = Publishers(z)
                try:
                    if not pubs.wait_matching(self.wait_keys, 20.0):
                        raise TimeoutError("the feed never subscribed")
                    for key, payload in self.plan:
                        pubs.put(key, payload)
                    self.done.wait(30.0)
                finally:
                    pubs.close()
        except BaseException as exc:  # reported by the test
            self.error = exc
        finally:
            self.ready.set()


def _run(feed, port, plan, wait_keys) -> list:
    pub = _Publisher(port, plan, wait_keys)
    with feed:
        pub.start()
        try:
            blocks = list(feed)
        finally:
            pub.done.set()
            pub.join(30)
    assert pub.error is None, pub.error
    return blocks


def test_live_feed_yields_what_was_published_with_gaps_and_selection():
    port = free_tcp_port()
    dets = ["b0m0c002", "b0m0c000", "b0m1c001"]
    feed = LivePowerFeed(loopback(listen_port=port), "t", detectors=dets, idle_timeout_s=1.5, duration_s=60)
    sent0 = [0, 1, 2, 4, 4, 5, 3]  # module 0: seq 3 lost, 4 repeated, then 3 arrives late
    plan = []
    for step in range(7):
        plan.append((keys.power_key("t", 0, 0), chunk(sent0[step], 0).to_bytes()))
        if step < 3:
            plan.append((keys.power_key("t", 0, 1), chunk(step, 1).to_bytes()))
            plan.append((keys.power_key("t", 0, 2), chunk(step, 2).to_bytes()))
    plan.insert(3, (keys.power_key("t", 0, 0), b"\x92not a power chunk"))
    t0 = time.monotonic()
    blocks = _run(feed, port, plan, [keys.power_key("t", 0, 0), keys.power_key("t", 0, 1)])
    assert time.monotonic() - t0 < 30 and feed._session is None  # bounded, and closed
    m0 = [b for b in blocks if b.module == 0]
    m1 = [b for b in blocks if b.module == 1]
    assert not [b for b in blocks if b.module == 2]  # not subscribed
    assert [b.n_samples for b in m0] == [N] * 6 and [b.n_samples for b in m1] == [N] * 3
    assert all(b.detectors == ("b0m0c002", "b0m0c000") for b in m0) and m1[0].detectors == ("b0m1c001",)
    expect = [0, 1, 2, None, 4, 5]  # None: the hole left by seq 3
    for b, s in zip(m0, expect):
        assert b.first_sample == m0.index(b) * N
        if s is None:
            assert np.all(b.flags == fl.GAP) and np.all(np.isnan(b.p_opt_w))
            np.testing.assert_array_equal(b.t_ns, chunk(3).times_ns())
        else:
            c = chunk(s)
            np.testing.assert_array_equal(b.t_ns, c.times_ns())
            np.testing.assert_array_equal(bits(b.p_opt_w), bits(c.p_opt_w[[2, 0]]))
            np.testing.assert_array_equal(b.flags, c.flags[[2, 0]])
    for b, s in zip(m1, range(3)):
        np.testing.assert_array_equal(bits(b.p_opt_w), bits(chunk(s, 1).p_opt_w[[1]]))
    st = feed.stats["t_b0m0"]
    # seq 3 came late: not lost (seq_gaps 0), but its samples are overlap behind the NaN fill.
    assert (st.duplicate_chunks, st.overlap_samples, st.gap_samples, st.seq_gaps) == (1, N, N, 0)
    assert feed.invalid_messages == 1


def test_live_feed_without_selection_grows_rows_and_stops_at_max_blocks():
    port = free_tcp_port()
    plan = [(keys.power_key("t", 0, 0), chunk(s, channels=(0, 1) if s < 2 else (0, 1, 3)).to_bytes()) for s in range(6)]
    feed = LivePowerFeed(loopback(listen_port=port), "t", max_blocks=4, idle_timeout_s=10)
    blocks = _run(feed, port, plan, [plan[0][0]])
    assert len(blocks) == 4
    assert blocks[1].detectors == ("b0m0c000", "b0m0c001")
    assert blocks[2].detectors == blocks[3].detectors == ("b0m0c000", "b0m0c001", "b0m0c003")
    c = chunk(3, channels=(0, 1, 3))
    np.testing.assert_array_equal(bits(blocks[3].p_opt_w), bits(c.p_opt_w))
    assert feed._session is None


def test_live_feed_takes_board_and_module_as_the_recorded_feed_does():
    """``board``/``module``: a number or None (any), as RecordedPower; the old ``"*"`` string is one line."""
    z = loopback(listen_port=free_tcp_port())  # not joined: only the subscription is worked out
    assert LivePowerFeed(z, "t").key_exprs == [keys.power_key("t", "*", "*")]
    assert LivePowerFeed(z, "t", board=2).key_exprs == [keys.power_key("t", 2, "*")]
    assert LivePowerFeed(z, "t", module=5).key_exprs == [keys.power_key("t", "*", 5)]
    for bad in ("*", -1, True):
        with pytest.raises(ConfigError, match="board .*expected a number >= 0, or None"):
            LivePowerFeed(z, "t", board=bad)


def test_live_hole_comes_in_bounded_blocks_and_a_corrupt_time_does_not_end_the_stream():
    port = free_tcp_port()
    hole_s = 100
    t1 = T0 + STEP + hole_s * 10**9
    sent = [chunk(0), chunk(1, t0_ns=t1), chunk(2, t0_ns=9 * 10**18), chunk(3, t0_ns=t1 + STEP)]
    plan = [(keys.power_key("t", 0, 0), c.to_bytes()) for c in sent]
    feed = LivePowerFeed(loopback(listen_port=port), "t", idle_timeout_s=1.5, duration_s=60, gap_block_samples=4096)
    blocks = _run(feed, port, plan, [plan[0][0]])
    n_fill = hole_s * int(RATE)
    assert [b.n_samples for b in blocks] == [N, 4096, 4096, n_fill - 8192, N, N, N]
    assert all(np.all(b.flags == fl.GAP) and b.table_identities == () for b in blocks[1:4])
    np.testing.assert_array_equal(np.concatenate([b.t_ns for b in blocks[1:4]]),
                                  T0 + np.rint(np.arange(N, N + n_fill) * 1e9 / RATE).astype(np.int64))
    for b, c in zip([blocks[0], *blocks[4:]], sent):
        np.testing.assert_array_equal(b.t_ns, c.times_ns())
        np.testing.assert_array_equal(bits(b.p_opt_w), bits(c.p_opt_w))
        assert b.table_identities == ("tab-1",)
    st = feed.stats["t_b0m0"]
    assert st.segment_starts == [2 * N + n_fill, 3 * N + n_fill] and st.overlap_samples == 0


def _readme_section_code(title: str) -> str:
    text = (Path(__file__).resolve().parents[1] / "docs" / "feeds.md").read_text()
    section = text.split(f"\n## {title}\n", 1)[1].split("\n## ", 1)[0]
    blocks = re.findall(r"```python\n(.*?)```", section, re.S)
    assert blocks, f"no python example in docs/feeds.md section {title!r}"
    return "\n".join(blocks)


def test_readme_feeds_examples_run(tmp_path, monkeypatch):
    """docs/feeds.md's code, as written, on recordings it names and a live publisher."""
    monkeypatch.chdir(tmp_path)
    sent = [chunk(s, module=3, channels=(1, 2, 7), setup="lab") for s in range(12) if s != 5]
    half = len(sent) // 2
    write(tmp_path / "a.mcap", sent[:half])
    write(tmp_path / "b.mcap", sent[half:])
    with RotatingMcapWriter(tmp_path / "recordings", "s", rotate_bytes=2000, rotate_s=0) as w:
        for c in sent:
            w.write(keys.power_key("lab", 0, 3), c.to_bytes(), T0 + (c.seq + 1) * STEP)
    port = free_tcp_port()
    live = [chunk(s, module=3, channels=(1, 7), setup="lab", t0_ns=T0 + 10**12 + s * STEP) for s in range(3)]
    pub = _Publisher(port, [(keys.power_key("lab", 0, 3), c.to_bytes()) for c in live],
                     [keys.power_key("lab", 0, 3)], listen=True)
    pub.start()
    assert pub.ready.wait(20)
    ns = {"t0": T0 + 2 * STEP, "t1": T0 + 9 * STEP, "endpoint": f"tcp/127.0.0.1:{port}"}
    code = _readme_section_code("Feeds for mapmaking")
    # A fragment says so, and names what it leaves to the reader: exactly what this test gives it (issue 34).
    said = re.search(r"# A fragment: (.*?) are yours", code, re.S)
    assert said and set(re.findall(r"\b(t0|t1|endpoint)\b", said.group(1))) == set(ns), code[:300]
    try:
        exec(compile(code, "docs/feeds.md", "exec"), ns)
    finally:
        pub.done.set()
        pub.join(30)
    assert pub.error is None, pub.error
    b = ns["b"]
    assert b.detectors == ("b0m3c001", "b0m3c007") and b.n_samples == 7 * N
    assert np.all(b.flags[:, 3 * N:4 * N] == fl.GAP)  # chunk 5 never recorded
    assert sorted(ns["obs"]) == ["lab_b0m3"] and ns["obs"]["lab_b0m3"].n_samples == 12 * N
    np.testing.assert_array_equal(bits(ns["obs"]["lab_b0m3"].p_opt_w[:, :N]), bits(sent[0].p_opt_w))
    assert ns["blk"].name == "lab_b0m3" and ns["blk"].detectors == ("b0m3c001",)  # the live feed's last block
    np.testing.assert_array_equal(bits(ns["blk"].p_opt_w), bits(live[-1].p_opt_w[[0]]))

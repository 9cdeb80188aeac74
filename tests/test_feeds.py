"""Recorded power feeds on real MCAP files: exact round trip, gaps, selection, rotation, HDF5 export."""

from __future__ import annotations

import json

import h5py
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mntes_stream.cli import main as cli_main
from mntes_stream.core import flags as fl
from mntes_stream.core.align import sample_times_ns
from mntes_stream.core.ids import detector_id
from mntes_stream.errors import ConfigError
from mntes_stream.feeds import RecordedPower, export_hdf5, iter_power_blocks, read_hdf5, read_power
from mntes_stream.feeds.blocks import BlockBuffer, GapFill, StreamAssembler, StreamId, iter_pieces
from mntes_stream.io import keys
from mntes_stream.io.mcap import McapFileWriter, RotatingMcapWriter
from mntes_stream.io.messages import PowerChunk, Provenance

T0 = 1_700_000_000_000_000_000
RATE = 100.0
N = 10  # samples per chunk
STEP = int(N * 1e9 / RATE)


def chunk(seq: int, module: int = 0, channels=(0, 1, 2, 3), setup: str = "t", t_ns=None, t0_ns=None,
          table: str = "tab-1", board: int = 0) -> PowerChunk:
    """A power chunk with distinct, NaN-bearing values (seeded by seq and module); t0 on the T0 grid by default."""
    ch = np.asarray(channels, dtype=np.int32)
    rng = np.random.default_rng([seq, module])
    p = rng.normal(1e-12, 1e-14, (ch.size, N))
    f = np.zeros((ch.size, N), np.uint16)
    f[:, 3] = fl.SATURATED
    p[:, 3] = np.nan
    f[0, 7] = fl.HK_STALE  # a flag that keeps its value
    t0 = T0 + seq * STEP if t0_ns is None else t0_ns
    times = {"t0_ns": t0, "sample_rate_hz": RATE} if t_ns is None else {"t0_ns": None, "sample_rate_hz": None, "t_ns": t_ns}
    return PowerChunk(setup=setup, board=board, module=module, channels=ch,
                      detector_ids=[detector_id(board, module, c) for c in ch], seq=seq, p_opt_w=p, flags=f,
                      table_identity=table, converter_kind="exact", source_t_pub_ns=T0, t_pub_ns=T0, **times)


def write(path, chunks, log_times=None):
    with McapFileWriter(path) as w:
        for k, c in enumerate(chunks):
            log = T0 + (c.seq + 1) * STEP if log_times is None else log_times[k]
            w.write(keys.power_key(c.setup, c.board, c.module), c.to_bytes(), log)
    return path


def bits(a):
    """Bit patterns of a float array (so NaN == NaN and -0.0 != 0.0)."""
    return np.ascontiguousarray(a, dtype=np.float64).view(np.uint64)


def assert_chunk_in(block, c, col0):
    """The columns of ``block`` from ``col0`` hold chunk ``c`` bitwise, rows matched by id."""
    rows = [block.detectors.index(d) for d in c.detector_ids]
    sl = slice(col0, col0 + c.n_samples)
    np.testing.assert_array_equal(block.t_ns[sl], c.times_ns())
    np.testing.assert_array_equal(bits(block.p_opt_w[rows, sl]), bits(c.p_opt_w))
    np.testing.assert_array_equal(block.flags[rows, sl], c.flags)


def test_round_trip_is_bitwise_and_gaps_are_nan_flagged(tmp_path):
    sent = [chunk(s) for s in range(12) if s not in (4, 5, 9)]
    b = read_power(write(tmp_path / "a.mcap", sent))
    assert b.n_samples == 12 * N and b.detectors == tuple(detector_id(0, 0, c) for c in range(4))
    np.testing.assert_array_equal(b.t_ns, sample_times_ns(T0, RATE, 12 * N))  # gaps continue the grid
    for c in sent:
        assert_chunk_in(b, c, c.seq * N)
    gap = np.zeros(12 * N, bool)
    for s in (4, 5, 9):
        gap[s * N:(s + 1) * N] = True
    assert np.all(b.flags[:, gap] == fl.GAP) and np.all(np.isnan(b.p_opt_w[:, gap]))
    assert not np.any(b.flags[:, ~gap] & fl.GAP)
    assert not np.any(b.p_opt_w == 0)  # never silent zeros
    rec = RecordedPower(tmp_path / "a.mcap")
    rec.read()
    st_ = next(iter(rec.stats.values()))
    assert (st_.gaps, st_.gap_samples, st_.seq_gaps, st_.chunks) == (2, 3 * N, 3, 9)


def test_out_of_order_and_duplicated_chunks_are_sorted_and_counted(tmp_path):
    order = [0, 2, 1, 3, 3, 5, 4, 6, 1]
    sent = [chunk(s) for s in order]
    logs = [T0 + k * STEP for k in range(len(order))]  # received in this (wrong) order
    rec = RecordedPower(write(tmp_path / "a.mcap", sent, logs))
    b = rec.read()["t_b0m0"]
    assert b.n_samples == 7 * N and np.all(np.diff(b.t_ns) > 0)
    for s in range(7):
        assert_chunk_in(b, chunk(s), s * N)
    st_ = rec.stats[b.stream]
    assert st_.duplicate_chunks == 2 and st_.gaps == 0 and st_.chunks == 7


def test_detectors_that_come_and_go_are_unknown_channel(tmp_path):
    sent = [chunk(0, channels=(0, 1, 2)), chunk(1, channels=(0, 1, 2, 5)), chunk(2, channels=(1, 2, 5))]
    b = read_power(write(tmp_path / "a.mcap", sent))
    assert b.detectors == ("b0m0c000", "b0m0c001", "b0m0c002", "b0m0c005")
    for c in sent:
        assert_chunk_in(b, c, c.seq * N)
    absent = {(3, 0), (0, 2)}  # (row, chunk): c005 not in chunk 0, c000 not in chunk 2
    for row, k in absent:
        assert np.all(b.flags[row, k * N:(k + 1) * N] == fl.UNKNOWN_CHANNEL)
        assert np.all(np.isnan(b.p_opt_w[row, k * N:(k + 1) * N]))


def test_time_and_detector_selection(tmp_path):
    path = write(tmp_path / "a.mcap", [chunk(s, m) for s in range(10) for m in (0, 1)])
    full = RecordedPower(path).read()
    assert sorted(full) == ["t_b0m0", "t_b0m1"]
    start, end = T0 + 23 * STEP // N, T0 + 71 * STEP // N  # sample 23 .. 70 inclusive
    b = read_power(path, detectors=["b0m1c002", "b0m1c000"], start_ns=start, end_ns=end)
    assert b.detectors == ("b0m1c002", "b0m1c000") and b.module == 1
    ref = full["t_b0m1"]
    keep = (ref.t_ns >= start) & (ref.t_ns < end)
    assert keep.sum() == 48
    np.testing.assert_array_equal(b.t_ns, ref.t_ns[keep])
    np.testing.assert_array_equal(bits(b.p_opt_w), bits(ref.p_opt_w[[2, 0]][:, keep]))
    np.testing.assert_array_equal(b.flags, ref.flags[[2, 0]][:, keep])
    with pytest.raises(ConfigError, match="b0m1c009"):
        read_power(path, detectors=["b0m1c009"])
    with pytest.raises(ConfigError, match="covers 2"):
        read_power(path)
    with pytest.raises(ConfigError, match="no power"):
        read_power(path, start_ns=T0 + 10**12)
    assert read_power(path, module=0).module == 0
    first = read_power(path, detectors=["b0m0c000"])  # the chunks' first row only: the others are left out
    np.testing.assert_array_equal(bits(first.p_opt_w), bits(full["t_b0m0"].p_opt_w[:1]))


def test_rotated_session_reads_as_one_and_blocks_stream(tmp_path):
    chunks = [chunk(s, m) for s in range(40) for m in (0, 1)]
    w = RotatingMcapWriter(tmp_path / "rot", "s", rotate_bytes=6000, rotate_s=0)
    for c in chunks:
        w.write(keys.power_key("t", 0, c.module), c.to_bytes(), T0 + (c.seq + 1) * STEP + c.module)
    w.close()
    files = sorted((tmp_path / "rot").glob("*.mcap"))
    assert len(files) >= 4
    single = write(tmp_path / "one.mcap", chunks)
    whole = RecordedPower(single).read()
    for source in (tmp_path / "rot", files, [str(f) for f in reversed(files)]):
        got = RecordedPower(source).read()
        for name, b in whole.items():
            np.testing.assert_array_equal(got[name].t_ns, b.t_ns)
            np.testing.assert_array_equal(bits(got[name].p_opt_w), bits(b.p_opt_w))
            np.testing.assert_array_equal(got[name].flags, b.flags)
    blocks = list(iter_power_blocks(tmp_path / "rot", block_samples=37))
    by = {}
    for blk in blocks:
        assert blk.n_samples <= 37 and blk.first_sample == sum(x.n_samples for x in by.get(blk.name, []))
        by.setdefault(blk.name, []).append(blk)
    for name, b in whole.items():
        np.testing.assert_array_equal(bits(np.concatenate([x.p_opt_w for x in by[name]], axis=1)), bits(b.p_opt_w))
        np.testing.assert_array_equal(np.concatenate([x.t_ns for x in by[name]]), b.t_ns)


def test_explicit_sample_times_and_overlap(tmp_path):
    t_a = T0 + np.arange(N, dtype=np.int64) * 7_000_000
    t_b = t_a[-1] + 7_000_000 * np.arange(-2, N - 2, dtype=np.int64)  # first 3 samples overlap chunk a
    t_c = t_b[-1] + 7_000_000 * np.arange(4, N + 4, dtype=np.int64)   # a hole of 3 samples
    sent = [chunk(0, t_ns=t_a), chunk(1, t_ns=t_b), chunk(2, t_ns=t_c)]
    rec = RecordedPower(write(tmp_path / "a.mcap", sent))
    b = rec.read()["t_b0m0"]
    assert np.all(np.diff(b.t_ns) > 0)
    st_ = rec.stats[b.stream]
    assert st_.overlap_samples == 3 and st_.gap_samples == 3
    assert_chunk_in(b, sent[0], 0)
    np.testing.assert_array_equal(bits(b.p_opt_w[:, N:2 * N - 3]), bits(sent[1].p_opt_w[:, 3:]))
    np.testing.assert_array_equal(b.flags[:, 2 * N - 3:2 * N], fl.GAP)
    assert_chunk_in(b, sent[2], 2 * N)


def test_export_hdf5_layout_provenance_and_exact_read_back(tmp_path):
    prov = Provenance(setup="t", params_toml='schema = "mntes-params"\nversion = 1\n', table_identity="tab-1",
                      converter_kind="exact", software_version="0.1.0", t_ns=T0)
    sent = [chunk(s, m) for s in range(30) for m in (0, 1) if (s, m) != (7, 1)]
    with McapFileWriter(tmp_path / "a.mcap") as w:
        w.write(keys.provenance_key("t"), prov.to_bytes(), T0)
        for c in sent:
            w.write(keys.power_key("t", 0, c.module), c.to_bytes(), T0 + (c.seq + 1) * STEP)
    summary = export_hdf5(tmp_path / "a.mcap", tmp_path / "x.h5", block_samples=64)
    assert summary.samples == 2 * 4 * 30 * N and summary.gap_samples == N
    with pytest.raises(ConfigError, match="exists"):
        export_hdf5(tmp_path / "a.mcap", tmp_path / "x.h5")
    ref = RecordedPower(tmp_path / "a.mcap").read()
    back = read_hdf5(tmp_path / "x.h5")
    assert sorted(back) == sorted(ref) == ["t_b0m0", "t_b0m1"]
    for name, b in ref.items():
        np.testing.assert_array_equal(bits(back[name].p_opt_w), bits(b.p_opt_w))
        np.testing.assert_array_equal(back[name].flags, b.flags)
        np.testing.assert_array_equal(back[name].t_ns, b.t_ns)
        assert back[name].detectors == b.detectors
        assert back[name].table_identities == b.table_identities == ("tab-1",)
    with h5py.File(tmp_path / "x.h5") as f:
        assert f.attrs["format"] == "mntes-stream/power"
        assert json.loads(f.attrs["source_files"]) == [str(tmp_path / "a.mcap")]
        p = f["provenance/0"].attrs
        assert p["params_toml"] == prov.params_toml and p["table_identity"] == "tab-1"
        g = f["t_b0m1"]
        assert json.loads(g.attrs["table_identities"]) == ["tab-1"] and json.loads(g.attrs["converter_kinds"]) == ["exact"]
        assert json.loads(g.attrs["segment_starts"]) == [] and f.attrs["max_gap_s"] == 3600.0
        assert json.loads(g.attrs["provenance"]) == ["/provenance/0"]
        assert json.loads(g.attrs["counts"])["gap_samples"] == N
        assert g["tod"].attrs["units"] == "W" and g["tod"].compression == "gzip" and g["tod"].chunks == (4, 64)
        np.testing.assert_array_equal(g["time"][()], g["time_ns"][()] / 1e9)
        assert json.loads(g["flags"].attrs["bits"])["gap"] == fl.GAP


def test_cli_export_with_selection(tmp_path, capsys):
    path = write(tmp_path / "a.mcap", [chunk(s, m) for s in range(10) for m in (0, 1)])
    start = T0 + 2 * STEP
    rc = cli_main(["export", str(path), "--out", str(tmp_path / "x.h5"), "--detectors", "b0m0c003,b0m0c001",
                   "--start", str(start), "--end", "2023-11-14T22:13:20.7Z", "--json"])
    assert rc == 0
    out = json.loads(capsys.readouterr().out)
    assert out["observations"] == ["t_b0m0"] and out["detector_samples"] == 2 * 5 * N
    b = read_hdf5(tmp_path / "x.h5", "t_b0m0")
    assert b.detectors == ("b0m0c003", "b0m0c001")
    assert b.t_ns[0] == start and b.t_ns[-1] == T0 + 7 * STEP - STEP // N  # end = T0 + 700 ms, exclusive
    assert cli_main(["export", str(path), "--out", str(tmp_path / "y.h5"), "--detectors", "b9m0c000"]) == 2


@settings(max_examples=60, deadline=None)
@given(
    present=st.lists(st.booleans(), min_size=2, max_size=25),
    dup=st.lists(st.integers(0, 24), max_size=4),
    seed=st.integers(0, 2**16),
)
def test_assembler_property_every_kept_sample_exact_every_hole_flagged(present, dup, seed):
    """Chunks in random order with drops and duplicates, sorted as the reader does."""
    kept = [s for s, ok in enumerate(present) if ok]
    if not kept:
        return
    feed = sorted(kept + [d for d in dup if d in kept])  # duplicates adjacent, as after the index sort
    asm = StreamAssembler([detector_id(0, 0, c) for c in range(4)], np.arange(4))
    pieces = []
    for s in feed:
        c = chunk(s)
        pieces += iter_pieces(asm.push(c.seq, c.times_ns(), c.sample_rate_hz, c.detector_ids, c.p_opt_w, c.flags), 7)
    assert max(x.t_ns.size for x in pieces) <= N  # gap fill in pieces of at most 7, chunks whole
    t = np.concatenate([p[0] for p in pieces])
    p = np.concatenate([p[1] for p in pieces], axis=1)
    f = np.concatenate([p[2] for p in pieces], axis=1)
    lo, hi = kept[0], kept[-1] + 1
    np.testing.assert_array_equal(t, sample_times_ns(T0 + lo * STEP, RATE, (hi - lo) * N))
    for s in range(lo, hi):
        cols = slice((s - lo) * N, (s - lo + 1) * N)
        if s in kept:
            c = chunk(s)
            np.testing.assert_array_equal(bits(p[:, cols]), bits(c.p_opt_w))
            np.testing.assert_array_equal(f[:, cols], c.flags)
        else:
            assert np.all(f[:, cols] == fl.GAP) and np.all(np.isnan(p[:, cols]))
    assert asm.stats.duplicate_chunks == len(feed) - len(kept)
    assert asm.stats.gap_samples == N * (hi - lo - len(kept))


def test_file_of_a_killed_recorder_reads_up_to_its_last_flush(tmp_path):
    import shutil

    from mntes_stream.io.mcap import TruncatedFileWarning

    w = McapFileWriter(tmp_path / "live.mcap", chunk_size_bytes=1024)
    for s in range(8):
        w.write(keys.power_key("t", 0, 0), chunk(s).to_bytes(), T0 + (s + 1) * STEP)
        w.flush()
    shutil.copy(tmp_path / "live.mcap", tmp_path / "cut.mcap")  # as a SIGKILL would leave it: no summary, no footer
    w.write(keys.power_key("t", 0, 0), chunk(8).to_bytes(), T0 + 9 * STEP)  # never flushed before the "kill"
    w.close()
    with pytest.warns(TruncatedFileWarning):
        b = read_power(tmp_path / "cut.mcap")
    assert b.n_samples == 8 * N
    for s in range(8):
        assert_chunk_in(b, chunk(s), s * N)


def test_long_hole_is_filled_in_bounded_blocks_and_longer_steps_are_reported_segment_breaks(tmp_path):
    """A 20 min hole: NaN + GAP in blocks of at most block_samples; a 10 h pause and a corrupt
    far-future timestamp (year 2255): segment breaks, reported, nothing allocated for them."""
    hole_ns, pause_ns, future_ns = 1200 * 10**9, 10 * 3600 * 10**9, 9 * 10**18
    t3 = T0 + 3 * STEP + hole_ns
    sent = [chunk(0), chunk(1), chunk(2), chunk(3, t0_ns=t3), chunk(4, t0_ns=t3 + STEP + pause_ns),
            chunk(5, t0_ns=t3 + 2 * STEP + pause_ns), chunk(6, t0_ns=future_ns)]
    path = write(tmp_path / "a.mcap", sent)
    n_fill = hole_ns * int(RATE) // 10**9
    rec = RecordedPower(path)
    blocks = list(rec.iter_blocks(block_samples=4096))
    assert max(b.n_samples for b in blocks) == 4096 and sum(b.n_samples for b in blocks) == 7 * N + n_fill
    st_ = rec.stats[StreamId("t", 0, 0)]
    starts = [3 * N + n_fill + N, 3 * N + n_fill + 3 * N]  # chunk 4 (after the pause) and chunk 6 (the corrupt time)
    assert st_.segment_starts == starts and (st_.gaps, st_.gap_samples) == (1, n_fill)
    b = RecordedPower(path).read()["t_b0m0"]
    fill = slice(3 * N, 3 * N + n_fill)
    np.testing.assert_array_equal(b.t_ns[fill], sample_times_ns(T0, RATE, 3 * N + n_fill)[3 * N:])  # the grid goes on
    assert np.all(b.flags[:, fill] == fl.GAP) and np.all(np.isnan(b.p_opt_w[:, fill]))
    cols = [0, N, 2 * N, 3 * N + n_fill, starts[0], starts[0] + N, starts[1]]
    for c, col in zip(sent, cols):
        assert_chunk_in(b, c, col)
    assert not np.any(b.flags[:, 3 * N + n_fill:] & fl.GAP)  # nothing filled across the breaks
    summary = export_hdf5(path, tmp_path / "x.h5", block_samples=4096)
    assert summary.segment_breaks == 2 and summary.gap_samples == n_fill
    with h5py.File(tmp_path / "x.h5") as f:
        assert json.loads(f["t_b0m0"].attrs["segment_starts"]) == starts
    # A shorter max_gap_s makes the 20 min hole a break too.
    short = RecordedPower(path, max_gap_s=600)
    short.read()
    assert short.stats[StreamId("t", 0, 0)].segment_starts == [3 * N, 4 * N, 6 * N] and short.stats[StreamId("t", 0, 0)].gaps == 0
    with pytest.raises(ConfigError, match="max_gap_s"):
        RecordedPower(path, max_gap_s=0)


def test_gap_fill_is_made_lazily_and_a_jump_back_starts_a_segment():
    dets = [detector_id(0, 0, c) for c in range(4)]
    asm = StreamAssembler(dets, np.arange(4), max_gap_s=10**6)
    c0 = chunk(0)
    asm.push(c0.seq, c0.times_ns(), RATE, c0.detector_ids, c0.p_opt_w, c0.flags)
    c1 = chunk(1, t0_ns=T0 + STEP + 150_000 * 10**9)  # a 41 h hole: 15 M samples x 4 detectors
    out = asm.push(c1.seq, c1.times_ns(), RATE, c1.detector_ids, c1.p_opt_w, c1.flags, "tab-1")
    fill = out[0]
    assert isinstance(fill, GapFill) and fill.size == 15_000_000 and asm.stats.gap_samples == fill.size
    buf = BlockBuffer(StreamId("t", 0, 0), dets, np.arange(4), block_samples=1000)
    blocks = buf.add(out)
    first = [next(blocks) for _ in range(3)]  # made on demand: 3 blocks, not the hole
    assert [b.n_samples for b in first] == [1000] * 3 and all(b.table_identities == () for b in first)
    np.testing.assert_array_equal(first[2].t_ns, sample_times_ns(T0, RATE, N + 3000)[N + 2000:])
    assert np.all(first[0].flags == fl.GAP)
    # A corrupt far-future chunk, then the stream as before: a break each way, nothing dropped.
    asm = StreamAssembler(dets, np.arange(4))
    pieces = []
    for c in (chunk(0), chunk(1), chunk(2, t0_ns=8 * 10**18), chunk(3), chunk(4)):
        pieces += iter_pieces(asm.push(c.seq, c.times_ns(), RATE, c.detector_ids, c.p_opt_w, c.flags), 100)
    assert [p.t_ns.size for p in pieces] == [N] * 5 and asm.stats.segment_starts == [2 * N, 3 * N]
    assert asm.stats.overlap_samples == 0 and asm.stats.gaps == 0
    # A corrupt sample rate: a 1 s hole at 1 GHz is beyond MAX_FILL_SAMPLES: a break, not 1e9 samples.
    asm = StreamAssembler(dets, np.arange(4))
    c0, c1 = chunk(0), chunk(1, t0_ns=T0 + 10**9)
    asm.push(0, c0.times_ns(), 1e9, c0.detector_ids, c0.p_opt_w, c0.flags)
    assert not any(isinstance(x, GapFill) for x in asm.push(1, c1.times_ns(), 1e9, c1.detector_ids, c1.p_opt_w, c1.flags))
    assert asm.stats.segment_starts == [N]


def test_blocks_carry_the_table_identities_of_their_power(tmp_path):
    sent = [chunk(s, table="tab-1" if s < 5 else "tab-2") for s in range(10) if s not in (7, 8)]
    path = write(tmp_path / "a.mcap", sent)
    blocks = list(iter_power_blocks(path, block_samples=2 * N))
    assert [b.table_identities for b in blocks] == [("tab-1",), ("tab-1",), ("tab-1", "tab-2"), ("tab-2",), ("tab-2",)]
    b = read_power(path)
    assert b.table_identities == ("tab-1", "tab-2") and b.select(["b0m0c001"]).table_identities == ("tab-1", "tab-2")
    assert read_power(path, start_ns=T0 + 6 * STEP).table_identities == ("tab-2",)
    export_hdf5(path, tmp_path / "x.h5")
    assert read_hdf5(tmp_path / "x.h5", "t_b0m0").table_identities == ("tab-1", "tab-2")
    # Blocks of gap fill only hold no table's power.
    gap_only = list(iter_power_blocks(path, block_samples=N))[7]
    assert np.all(gap_only.flags == fl.GAP) and gap_only.table_identities == ()

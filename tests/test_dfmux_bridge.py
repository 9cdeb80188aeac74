"""dfmux-bridge: IceBoard packets -> counts and housekeeping on zenoh (spt3g's DfMuxCollector + DfMuxBuilder).

The end-to-end test runs the real bridge (``mntes-stream dfmux-bridge``, its
own process), a synthetic sender (another process) and a zenoh subscriber in
a private network namespace, V2, V3 and V4 packets at the DfMux rate, and
checks every counts value against what was sent.
"""

from __future__ import annotations

import importlib.util

import numpy as np
import pytest

from mntes_stream.dfmux.assemble import RAIL, Assembler
from mntes_stream.dfmux.packets import SAMPLE_NS, PacketBuilder, header_dtype, irig_words, synthetic_counts

T0 = 1_790_000_000 * 10**9 // SAMPLE_NS * SAMPLE_NS


def _iq(board, module, nch, k):
    i, q = synthetic_counts(board, module, np.arange(nch), np.array([k]))
    out = np.empty(2 * nch, dtype=np.int32)
    out[0::2], out[1::2] = i[:, 0], q[:, 0]
    return out


def test_packets_are_what_the_collector_reads():
    """Sizes as DfMuxCollector expects (header 16 + nchan x 8 + 32), counts x 256, V4 blocks of 128."""
    for version, nch, n_pk in ((2, 64, 8), (3, 64, 8), (4, 128, 16)):
        b = PacketBuilder(version, 7, 2 if version == 4 else 8, 64)
        pk = b.packets(5, T0 + 5 * SAMPLE_NS)
        assert len(pk) == n_pk and {len(p) for p in pk} == {16 + nch * 8 + 32}
        rec = np.frombuffer(b"".join(pk), dtype=header_dtype(nch))
        assert (rec["version"] == version).all() and (rec["seq"] == 5).all()
        assert (rec["serial"] == (0 if version == 2 else 7)).all()
        i, _ = synthetic_counts(7, int(rec["module"][-1]), np.arange(nch) + (7 * 128 if version == 4 else 0),
                                np.array([5]))
        np.testing.assert_array_equal(rec["s"][-1, 0::2], i[:, 0] * 256)
    w = irig_words(np.array([T0]))[0]  # the collector adds the boards' missing second back
    assert w[5] == (T0 - 10**9) % 10**9 // 10 and 1 <= w[1] <= 366


def test_assembler_chunks_gaps_and_events():
    asm = Assembler("lab", chunk_samples=4, late_s=0.05)
    out = []
    for k in range(10):
        if 5 <= k < 7:  # board 1 skips two samples (a restart)
            mods = [(2, 0, 0, 1, _iq(2, 0, 3, k))]
        else:
            mods = [(1, 0, 0, 1, _iq(1, 0, 3, k)), (2, 0, 0, 1, _iq(2, 0, 3, k))]
        if k >= 8:  # module 2/1 starts late
            mods.append((2, 1, 0, 1, _iq(2, 1, 3, k)))
        out += asm.add(T0 + k * SAMPLE_NS, mods, 1)
    out += asm.flush(2)
    assert asm.stream_gaps == {"1/0": 2}
    kinds = [e.kind for e in asm.events]
    assert kinds == ["gap", "late"], asm.events
    by = {}
    for c in out:
        by.setdefault((c.board, c.module), []).append(c)
        k = (c.t_ns - T0) // SAMPLE_NS
        i, q = synthetic_counts(c.board, c.module, c.channels, k)
        np.testing.assert_array_equal(c.counts_i, i)
        np.testing.assert_array_equal(c.counts_q, q)
    assert [c.n_samples for c in by[(1, 0)]] == [4, 4]
    assert [c.seq for c in by[(2, 0)]] == [0, 1, 2] and [c.n_samples for c in by[(2, 0)]] == [4, 4, 2]
    assert asm.published == {"1/0": 2, "2/0": 3, "2/1": 1}
    asm.add(T0 + 10 * SAMPLE_NS, [(2, 0, 0, 1, _iq(2, 0, 3, 10))])
    asm.add(T0 + 10 * SAMPLE_NS, [(2, 0, 0, 1, _iq(2, 0, 3, 10))])  # the same time again: dropped, counted
    assert asm.out_of_order == 1
    asm.t_newest_ns = T0 + 400 * SAMPLE_NS
    asm.check_silent(1.0)
    assert {e.text for e in asm.events if e.kind == "silent"} == {"board 1 stopped sending (nothing for 1 s of data "
                                                                  "time)", "board 2 stopped sending (nothing for 1 s "
                                                                  "of data time)"}


def test_held_gaps_are_lost_as_far_as_sequence_numbers_skipped_the_rest_a_time_jump():
    """A gap in a stream's time stamps is missing samples only where its packets' sequence numbers skipped (or the
    board restarted); the rest is the board's clock jumping (an event, in time_jumps, never missing). Each gap
    takes the sequence event read just before it was seen (the collector writes it before the builder sends)."""
    from mntes_stream.dfmux.spt3glog import SeqEvent

    asm = Assembler("lab", chunk_samples=4, hold_gaps=True)
    t = [T0 + k * SAMPLE_NS for k in range(4)]
    t += [t[-1] + 11 * SAMPLE_NS]                  # k=4: 10 samples missing, the sequence skipped 10: lost
    t += [t[-1] + 10**9 + SAMPLE_NS]               # k=5: 1 s forward, no sequence skip: a jump
    t += [t[-1] + 10**9 + 4 * SAMPLE_NS]           # k=6: 1 s forward with 3 packets skipped: 3 lost, the rest a jump
    t += [t[-1] + 6 * SAMPLE_NS]                   # k=7: a restart (sequence back to 0): all 5 missing
    wall = [10**18 + k * 10**9 for k in range(len(t))]  # when the bridge took each sample
    for k, tk in enumerate(t):
        asm.add(tk, [(3, 1, 0, 1, _iq(3, 1, 2, k)), (3, 2, 0, 1, _iq(3, 2, 2, k))], wall[k])
    assert asm.stream_gaps == {} and len(asm.pending_gaps) == 8  # nothing counted before the sequence is known
    seq = [SeqEvent(3, m, got, exp, wall[k] - 10**6) for k, got, exp in ((4, 14, 4), (6, 19, 16), (7, 0, 21))
           for m in (1, 2)]
    asm.resolve_gaps(seq, upto=4)                  # module 1's and 2's first two gaps
    assert asm.stream_gaps == {"3/1": 10, "3/2": 10} and len(asm.pending_gaps) == 4
    assert [(j["board"], j["forward_s"]) for j in asm.time_jumps] == [(3, 1.0)], asm.time_jumps
    asm.resolve_gaps([])
    assert asm.stream_gaps == {"3/1": 18, "3/2": 18}, asm.stream_gaps
    assert [(j["board"], j["forward_s"]) for j in asm.time_jumps] == [(3, 1.0), (3, 1.0)], asm.time_jumps
    n_jump = round(10**9 / SAMPLE_NS)
    assert asm.jump_samples == 2 * 2 * n_jump  # two modules, each 1 s twice (the second's 3 lost samples apart)
    assert [e.kind for e in asm.events] == ["gap", "jump", "gap", "jump", "gap"], asm.events
    # without any sequence event every gap is a jump: nothing missing
    quiet = Assembler("lab", chunk_samples=4, hold_gaps=True)
    for k, tk in enumerate(t):
        quiet.add(tk, [(3, 1, 0, 1, _iq(3, 1, 2, k))], wall[k])
    quiet.resolve_gaps([])
    assert quiet.stream_gaps == {} and len(quiet.time_jumps) == 4


def test_spt3g_log_lines_are_classified_as_its_collector_and_builder_write_them():
    from mntes_stream.dfmux.spt3glog import SeqEvent, classify

    lines = {
        "ERROR (DfMuxCollector) 28-Nov-2026:15:16:44 UTC: Corrupted packet from 127.0.0.1 begins with 0 instead of "
        "0x666d7578 (DfMuxCollector.cxx:311 in int DfMuxCollector::BookPacket(DfmuxPacket*, in_addr))": "magic",
        "\x1b[1;31mERROR (DfMuxCollector) 28-Nov-2026:15:16:44 UTC:\x1b[0m Unknown packet version 9 from 127.0.0.1 "
        "(\x1b[1mDfMuxCollector.cxx:339\x1b[0m in int f())": "version",  # a terminal's colours
        "ERROR (DfMuxCollector): Badly-sized packet with 64 channels from 127.0.0.1 (550 bytes should be 560) "
        "(DfMuxCollector.cxx:287 in f)": "length",  # no time stamps
        "DEBUG (DfMuxCollector) 28-Nov-2026:15:16:44 UTC: Received V3 data for board 99 not enumerated on listener "
        "for interface 127.0.0.1 (DfMuxCollector.cxx:332 in f)": "board not configured",
        "ERROR (DfMuxBuilder) 28-Nov-2026:15:16:44 UTC: Duplicate packet from board 10 module 1/0 at time x "
        "(DfMuxBuilder.cxx:137 in f)": "duplicate",
        "WARN (DfMuxBuilder) 28-Nov-2026:15:16:44 UTC: Abandoning missing packets (x, data from 1/2 boards received)"
        " (DfMuxBuilder.cxx:196 in f)": "spt3g",
        "dfmux-bridge: board 10: packets refused": None,
    }
    for line, kind in lines.items():
        assert classify(line)[1] == kind, line
    level, kind, ev = classify("WARN (DfMuxCollector) 28-Nov-2026:15:16:44 UTC: Out-of-order packet from 10/7 (30 "
                               "instead of 20) (DfMuxCollector.cxx:352 in f)")
    assert (level, kind) == ("WARN", "seq") and ev == SeqEvent(10, 7, 30, 20, ev.t_read_ns) and ev.t_read_ns > 0
    _, kind, (board, step_s, _) = classify(
        "WARN (DfMuxBuilder) 28-Nov-2026:15:16:44 UTC: Bogon packet from board 10 at past time "
        "28-Nov-2026:16:16:39.733440000 (last outbound frame was at 28-Nov-2026:16:16:44.726886400) (x.cxx:107 in f)")
    assert kind == "before the builder's last sample" and board == 10
    assert abs(step_s - (4.9934464 + SAMPLE_NS / 1e9)) < 1e-6


def test_assembler_v4_missing_block_is_rail():
    asm = Assembler("lab", chunk_samples=1)
    blocks = [(9, 0, blk, 8, np.full(256, blk, dtype=np.int32)) for blk in range(8) if blk != 3]
    (c,) = asm.add(T0, blocks)
    assert c.channels.size == 1024
    assert (c.counts_i[3 * 128:4 * 128] == RAIL).all() and (c.counts_i[4 * 128:5 * 128] == 4).all()
    assert asm.invalid_samples == 128


def test_detector_board_is_the_simulators_detectors_with_one_bias_a_module():
    """The sender's detectors: the simulator's, named as the bridge publishes them, one bias per module (stated
    exactly as the bridge's --bias), in the transition at it (R/R_n 0.4-0.95) but the saturated ones, counts
    in the 24-bit word and x 256 in the packets; the same arguments give the same detectors."""
    from mntes_stream.core import model
    from mntes_stream.core.params import ParamArray
    from mntes_stream.core.sim import CHANNEL_OK, CHANNEL_SATURATED
    from mntes_stream.dfmux.bridge import bias_table
    from mntes_stream.dfmux.detectors import COUNTS_MAX, DetectorBoard

    board = DetectorBoard(10, 8, 16)
    assert [p.detector_id for p in board.params] == [f"b10m{m}c{c:03d}" for m in range(8) for c in range(16)]
    v = np.array([p.v_thev_v for p in board.params]).reshape(8, 16)
    assert np.all(v == board.bias_v[:, None]) and np.ptp(board.bias_v) > 0
    args = board.bias_args()
    assert args[0::2] == ["--bias"] * 8 and bias_table(args[1::2]) == [(10, m, float(x)) for m, x in
                                                                        enumerate(board.bias_v)]
    blk, ci, cq = board.next_counts(200)
    kinds = np.array([ch.kind for ch in board.sim.channels])
    assert set(kinds) == {CHANNEL_OK, CHANNEL_SATURATED} and np.sum(kinds == CHANNEL_SATURATED) == 8
    ok = kinds == CHANNEL_OK
    assert np.all(blk.truth_state == model.STATE_TRANSITION)  # the saturated ones on the arctan's tail
    pa = ParamArray.from_params(list(board.params))
    op = model.solve_operating_point(pa, blk.truth_p_opt_w, blk.truth_t_bath_k[None, :], 0.0, blk.truth_v_thev_v,
                                     sequential=True)
    r_frac = op.r_ohm / np.asarray(pa.transition.r_n_ohm)
    assert 0.4 < r_frac[ok].min() and r_frac[ok].max() < 0.95, (r_frac[ok].min(), r_frac[ok].max())
    assert r_frac[~ok].min() > 0.99  # loading 3 x P_sat: (almost) normal
    assert np.all(blk.truth_t_bath_k == 0.1) and np.all(blk.truth_b_field_t == 0)
    assert ci.dtype == np.int32 and ci.shape == (8, 16, 200) and max(np.abs(ci).max(), np.abs(cq).max()) < COUNTS_MAX
    raw = PacketBuilder(3, 10, 8, 16).packets(0, T0, counts=(ci[:, :, 0], cq[:, :, 0]))
    rec = np.frombuffer(b"".join(raw), dtype=header_dtype(16))
    assert np.array_equal(rec["s"][:, 0::2], ci[:, :, 0] * 256) and np.array_equal(rec["s"][:, 1::2], cq[:, :, 0] * 256)
    again = DetectorBoard(10, 8, 16)
    assert again.params == board.params and np.array_equal(again.next_counts(200)[1], ci)
    assert DetectorBoard(11, 8, 16).params[0].transition != board.params[0].transition  # each board its own


def test_bad_settings_are_one_line_errors(capsys):
    """Checked before spt3g is loaded: rc 2, one line, no traceback."""
    from mntes_stream.cli import main

    cases = [(["--interface", "127.0.0.1"], "name the boards"),
             (["--board", "3"], "give --interface"),
             (["--board", "3", "--interface", "10.255.255.1"], "cannot join 239.192.0.2"),
             (["--board", "3", "--interface", "127.0.0.1", "--bias", "3/x=1"], "bias entry"),
             (["--v2-board", "nohost=3", "--interface", "127.0.0.1"], "expected IP=SERIAL"),
             (["--board", "3", "--interface", "127.0.0.1", "--board-host", "3=h:x"], "expected SERIAL=HOST[:PORT]"),
             (["--board", "3", "--interface", "127.0.0.1", "--board-host", "4=h"], "not named by --board")]
    for argv, text in cases:
        assert main(["dfmux-bridge", *argv, "--duration", "1"]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and text in err[0], (argv, err)


@pytest.fixture(scope="module")
def netns():
    if importlib.util.find_spec("spt3g") is None:
        pytest.skip("spt3g not installed (the g3 extra)")
    from mntes_stream.bench.dfmux import netns_reason

    reason = netns_reason()
    if reason:
        pytest.skip(reason)


def test_bridge_v2_v3_v4_counts_one_by_one(netns, tmp_path):
    """16 V3 modules x 64 channels, a V2 board (8 x 64, named by its IP) and a V4 board (1 module, 8 blocks of 128)
    at the DfMux rate: every value as sent; a board restart in the ledger and the final line; a board that
    stops is reported and nothing fails."""
    from mntes_stream.bench.dfmux import run_netns

    cfg = tmp_path / "bridge.toml"
    cfg.write_text('[dfmux-bridge]\nsilent_s = 0.1\nhk_stale_s = 0.3\n')
    spec = {"boards": ["3:10:8:64", "3:11:8:64", "4:20:1", "2:5:8:64:127.0.0.2"], "duration_s": 1.2,
            "skip": ["11:40:60", "5:150:100000"], "restart": [11], "bridge_args": ["--config", str(cfg)]}
    r = run_netns(spec, timeout_s=90)
    assert r["bridge_rc"] == 0, r["bridge_stderr"]
    assert r["samples_missing"] == 0 and r["samples_unexpected"] == 0 and r["wrong"] == 0, r
    assert r["streams"] == 25 and r["values"] == (8 * 64 * (183 + 163) + 1024 * 183 + 8 * 64 * 150) * 1
    assert r["sender"]["samples"] == 183
    last = r["bridge_stdout"][-1]
    # board 11: 20 samples on 8 modules never received = 2 chunks of 16 each; nothing published is lost
    assert last.startswith("dfmux-bridge done: ") and "never received 16; lost 16 of" in last, last
    assert "160 module samples never received" in last, last
    text = "\n".join(r["bridge_stdout"])
    assert "board 11: up to 20 samples missing" in text and "board 5 stopped sending" in text, text
    # no tuber answers here (no /etc/hosts entry, no network): one line per board, counted, counts unaffected
    for serial in (10, 11):
        assert text.count(f"board {serial}: housekeeping from iceboard{serial:04d}.local:80 not read: name does not "
                          "resolve") == 1, text
    assert "board housekeeping reads failed" in last, last
    assert "spt3g 1.0.2" in r["bridge_stdout"][0]
    # a board never read holds no housekeeping to go stale: no readout flags (HK_STALE) and no bias from it
    # (hk_stale_s 0.3: a board read once would be flagged within the run)
    assert r["hk_messages"] > 0 and "readout_flags" not in r["hk_sensors"], r
    assert "no good housekeeping" not in text and "board housekeeping read " not in last, text


def test_hostile_packets_are_counted_by_reason_and_time_jumps_are_not_loss(netns):
    """Packets spt3g drops (magic, version, truncated, oversized, an unconfigured board), a packet claiming module
    200, an IRIG jump of 1 h forward and a step 5 s back: each dropped packet counted by its reason in the JSON and
    the closing line, module 200 refused (never a stream), the jump forward no loss, the step back named."""
    import json

    from mntes_stream.bench.dfmux import run_netns
    from mntes_stream.dfmux.bridge import ledger_line

    bad = ["magic:10:20", "version:10:30", "short:10:40", "long:10:50", "board:10:60", "module:10:70"]
    spec = {"boards": ["3:10:8:64"], "duration_s": 1.5, "verify": False, "bridge_args": ["--json"],
            "sender_args": [a for k in bad for a in ("--bad", k)] + ["--shift", "10:100:3600", "--shift", "10:180:-5"]}
    r = run_netns(spec, timeout_s=90)
    assert r["bridge_rc"] == 0, r["bridge_stderr"]
    out = json.loads("\n".join(r["bridge_stdout"]))
    n = r["sender"]["samples"]
    assert out["dropped_packets"] == {"magic": 1, "version": 1, "length": 2, "board not configured": 1,
                                      "module out of range (board 10)": 1,
                                      "before the builder's last sample": (n - 180) * 8}, out["dropped_packets"]
    assert sorted(out["published"]) == [f"10/{m}" for m in range(8)]  # no stream 10/200
    # the one sample of module 7 whose packet claimed module 200 is missing; the hour forward is not
    assert out["stream_gaps"] == {"10/7": 1} and out["lost"] == 1, (out["stream_gaps"], out["ledger"])
    assert [(j["board"], j["forward_s"]) for j in out["time_jumps"]] == [(10, 3600.0), (10, -5.0)], out["time_jumps"]
    assert out["jump_samples"] == round(3600e9 / SAMPLE_NS) * 8
    line = ledger_line(out)
    assert "lost 1 of " in line and "1 module samples never received" in line, line
    back = (n - 180) * 8
    assert (f"; {back + 6} packets dropped (before the builder's last sample {back}, board not configured 1, length 2, "
            "magic 1, module out of range (board 10) 1, version 1)" in line), line
    assert "2 time stamp jumps (board 10 +3600.000 s, board 10 -5.000 s; " in line, line
    # spt3g's own lines: shown (a few of each kind, at the level asked for), never the unconfigured board's
    err = "\n".join(r["bridge_stderr"])
    assert "Corrupted packet" in err and "not enumerated" not in err, err


def test_bridge_carries_the_detectors_power(netns, tmp_path):
    """The synthetic board's detectors (the simulator's) through packets, spt3g's collector and the bridge: the
    published counts are the simulator's, the published bias is the sender's, and the counts converted with the
    sender's parameter file give the simulator's optical power within the readout noise (its own prediction:
    sigma_P = sigma_I / |dI/dP|); the saturated channel is flagged."""
    import math

    from mntes_stream.bench.dfmux import run_netns
    from mntes_stream.core import model
    from mntes_stream.core.convert import EnvironmentBlock, ExactConverter
    from mntes_stream.core.flags import SATURATED
    from mntes_stream.core.params import ParamArray
    from mntes_stream.core.sim import CHANNEL_SATURATED
    from mntes_stream.dfmux.detectors import DetectorBoard
    from mntes_stream.io.messages import decode
    from mntes_stream.io.paramfile import load_params

    n_mod, n_ch = 8, 8  # a V3 board sends 8 modules (spt3g's collector waits for all 8)
    board = DetectorBoard(12, n_mod, n_ch)  # what the sender simulates for --board 3:12:8:8 (seed 0)
    spec = {"boards": [f"3:12:{n_mod}:{n_ch}"], "duration_s": 1.0, "verify": False, "bias": board.bias_args(),
            "sender_args": ["--counts", "detector", "--params-out", str(tmp_path / "p.toml")],
            "messages_out": str(tmp_path / "m.npz")}
    r = run_netns(spec, timeout_s=90)
    assert r["bridge_rc"] == 0 and r["samples_missing"] == 0 and r["samples_unexpected"] == 0, r
    assert r["sender"]["bias_v"] == {f"12/{m}": float(v) for m, v in enumerate(board.bias_v)}
    with np.load(tmp_path / "m.npz") as z:
        cut = np.cumsum(np.r_[0, z["sizes"]])
        msgs = [(str(k), decode(z["payloads"][a:b].tobytes())) for k, a, b in zip(z["keys"], cut[:-1], cut[1:])]
    bias = {(m.board, m.module): m.value for k, m in msgs if "/hk/bias/" in k}
    assert set(bias) == {(12, m) for m in range(n_mod)} and all(np.all(v == board.bias_v[m]) for (_, m), v in bias.items())
    assert {float(m.value[0]) for k, m in msgs if k.endswith("/hk/t_bath")} == {0.1}
    n = r["sender"]["samples"]
    blk, ci, cq = board.next_counts(n)  # the truth, sample by sample
    params = load_params(tmp_path / "p.toml")
    assert list(params) == [p.detector_id for p in board.params]
    conv = ExactConverter(list(params.values()))
    pa = ParamArray.from_params(list(board.params))
    v = np.repeat(board.bias_v, n_ch)[:, None]
    op = model.solve_operating_point(pa, blk.truth_p_opt_w, 0.1, 0.0, v, sequential=True)
    sigma_i = board.config.nei_a_rthz * math.sqrt(board.sim.fs / 2)  # per quadrature, A
    sigma_p = sigma_i / np.abs(model.small_signal(pa, op.r_ohm, 0.1, 0.0, v).di_dp_a_per_w)
    kinds = [ch.kind for ch in board.sim.channels]
    zs = []
    for k, m in msgs:
        if "/counts/" not in k:
            continue
        ks = (m.times_ns() - r["sender"]["t0_ns"]) // SAMPLE_NS
        rows = slice(n_ch * m.module, n_ch * (m.module + 1))
        assert np.array_equal(m.counts_i, ci[m.module][:, ks]) and np.array_equal(m.counts_q, cq[m.module][:, ks])
        ids = [f"b12m{m.module}c{c:03d}" for c in m.channels]
        env = EnvironmentBlock(t_bath_k=np.full(ks.size, 0.1), b_field_t=np.zeros(ks.size),
                               v_thev_v=bias[(12, m.module)].ravel())
        pb = conv.convert(ids, m.counts_i, m.counts_q, env)
        for c in range(n_ch):
            if kinds[rows][c] == CHANNEL_SATURATED:
                assert np.all(pb.flags[c] & SATURATED)
                continue
            assert np.all(pb.flags[c] == 0)
            z = (pb.p_opt_w[c] - blk.truth_p_opt_w[rows][c, ks]) / sigma_p[rows][c, ks]
            assert np.all(np.abs(z) < 6), (ids[c], np.abs(z).max())
            zs.append(z)
    z = np.concatenate(zs)
    assert z.size == n_mod * (n_ch - 1) * n  # every sample of every tuned channel
    # the error is the readout noise the simulator added, seen in power: its spread as predicted, no bias
    assert 0.85 < np.std(z) < 1.15 and abs(np.mean(z)) < 0.1, (np.std(z), np.mean(z))


def _crossbar() -> str | None:
    """crossbar as tests/test_ocs_bridge.py finds it: $MNTES_CROSSBAR, .crossbar/bin/crossbar, PATH."""
    import os
    import shutil
    import time
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    deadline = time.monotonic() + 600  # .ci/run installs it in the background: wait while it is on its way
    while (root / ".crossbar").is_dir() and not (root / ".crossbar/bin/crossbar").exists() \
            and not any((root / ".crossbar" / m).exists() for m in ("installed", "failed")) \
            and time.monotonic() < deadline:
        time.sleep(2)
    return os.environ.get("MNTES_CROSSBAR") or next(
        (str(p) for p in (root / ".crossbar/bin/crossbar",) if p.exists()), None) or shutil.which("crossbar")


@pytest.mark.slow
def test_lab_recipe_as_written(netns, tmp_path):
    """docs/dfmux.md's lab recipe, block as written, in a private network namespace: synthetic packets ->
    dfmux-bridge -> converter -> recorder -> monitor, the bath temperature from OCS (a crossbar router, ocs's
    fake-data agent, ocs-bridge), replay to a second recorder, export; nothing lost, every sample's bath from OCS."""
    import os
    import re
    import signal
    import subprocess
    import sys
    from pathlib import Path

    import h5py

    from mntes_stream.core.flags import HK_MISSING, HK_STALE, SATURATED, UNUSABLE
    from mntes_stream.core.ids import parse_detector_id
    from mntes_stream.core.sim import CHANNEL_SATURATED
    from mntes_stream.dfmux.detectors import DetectorBoard
    from mntes_stream.io.mcap import iter_messages
    from mntes_stream.io.messages import decode

    if importlib.util.find_spec("ocs") is None or importlib.util.find_spec("autobahn") is None:
        pytest.skip("the ocs extra (ocs, autobahn) is not installed")
    crossbar = _crossbar()
    if not crossbar:
        pytest.skip("no crossbar router (.ci/run installs it in .crossbar/; or set MNTES_CROSSBAR)")
    text = (Path(__file__).parents[1] / "docs" / "dfmux.md").read_text()
    (block,) = re.findall(r"```sh\n(.*?)```", text.split("## Lab recipe", 1)[1], re.S)
    (tmp_path / "recipe.sh").write_text(block)
    (tmp_path / "bin").mkdir()
    (tmp_path / "bin" / "crossbar").symlink_to(crossbar)  # crossbar alone on PATH, not its environment's python
    env = dict(os.environ, PATH=os.pathsep.join([str(Path(sys.executable).parent), str(tmp_path / "bin"),
                                                 os.environ.get("PATH", "")]))
    proc = subprocess.Popen(["unshare", "-n", "bash", "recipe.sh"], cwd=tmp_path, env=env, text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, start_new_session=True)
    try:
        out, _ = proc.communicate(timeout=240)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)  # the recipe's background services go with it
        out, _ = proc.communicate()
        pytest.fail(f"recipe did not finish in 240 s: {out[-2000:]}")
    logs = {p.name: p.read_text() for p in tmp_path.glob("*.log")}
    where = f"{out[-3000:]}\n" + "\n".join(f"== {k}\n{v[-800:]}" for k, v in logs.items())
    # crossbar's log is left out: its router worker logs a numpy ABI warning with a traceback, and runs on
    assert "Traceback" not in out and not any("Traceback" in v for k, v in logs.items() if k != "crossbar.log"), where
    assert "dfmux-bridge done: received 160 chunks: published 160; lost 0 of 160" in logs["bridge.log"], where
    # the bias came from the board (the stand-in's tuber): every module's, none disagreeing, no read failed
    last = logs["bridge.log"].strip().splitlines()[-1]
    assert re.search(r"; board housekeeping read [1-9]\d* times, the bias of 8 modules from the boards(;|$)", last), where
    assert "failed" not in last and "disagree" not in last, where
    assert "converter converter: received 160 chunks: converted 160; lost 0 of 160" in logs["converter.log"], where
    assert "ledger: counts received 160 chunks: recorded 160; lost 0 of 160" in logs["record.log"], where
    assert "ledger: counts received 160 chunks: recorded 160; lost 0 of 160" in logs["replayed.log"], where
    assert re.search(r"^\s*10/7\s+\d+", logs["monitor.log"], re.M), where  # the monitor saw the last module
    assert re.search(r"detector_samples: 39040$", out, re.M), where  # 305 samples x 128 detectors exported
    # the bath temperature came from OCS: the ocs-bridge's messages are the recording's t_bath, each of them
    m = re.search(r"ocs-bridge done: t_bath (\d+) readings in (\d+) messages; router joined, 1 connections, 0 failed",
                  logs["ocs-bridge.log"])
    assert m and int(m[1]) >= 10 and int(m[2]) >= 1, where
    assert re.search(rf"^\s*{m[2]}\s+mntes/lab/hk/t_bath$", out, re.M), where
    shown = [float(v) for v in re.findall(r"housekeeping: t_bath (\d+\.\d+) mK", logs["monitor.log"])]
    assert shown and all(50 < v < 150 for v in shown) and len(set(shown)) > 1, shown  # the agent's walk near 0.1 K
    assert proc.returncode == 0, where
    # the synthetic board's detectors: 15 a module in the transition, the 16th saturated (loading 3 x P_sat)
    assert re.search(r"^states: transition 120  saturated 8  superconducting 0  flagged 0", out, re.M), where
    with h5py.File(tmp_path / "lab.h5", "r") as f:  # one group a module
        groups = [([d.decode() if isinstance(d, bytes) else str(d) for d in f[g]["detectors"][()]], f[g]["tod"][()],
                   f[g]["flags"][()]) for g in f if "flags" in f[g]]
    flags = [fl for _, _, fl in groups]
    assert sum(fl.size for fl in flags) == 39040
    board = DetectorBoard(10, 8, 16)  # the sender's detectors (same arguments)
    truth = {p.detector_id: p for p in board.params}
    # the recorded bias is the board's, read over tuber: the detectors' own, on each module's 64 channels
    bias = [(m.module, m.value) for r in iter_messages(tmp_path / "rec") if r.schema_name == "mntes.hk"
            for m in [decode(r.payload)] if m.sensor == "bias"]
    assert sorted({m for m, _ in bias}) == list(range(8)), bias
    for m, v in bias:
        assert v.shape[1] == 64 and np.allclose(v, board.bias_v[m], rtol=1e-14, atol=0), (m, v)
    kinds = {ch.channel: ch.kind for ch in DetectorBoard(10, 1, 16).sim.channels}
    # the bath the converter used: OCS's readings, recorded; P = K (T^n - T_bath^n), so a bath dT away from the
    # sender's shifts the power by exactly K (T_sender^n - T_ocs^n), whatever the detector's T
    t_ocs = np.concatenate([np.ravel(m.value) for r in iter_messages(tmp_path / "rec") if r.schema_name == "mntes.hk"
                            for m in [decode(r.payload)] if m.sensor == "t_bath"])
    assert t_ocs.size and np.all((0.05 < t_ocs) & (t_ocs < 0.15)), t_ocs  # the recipe's tables' range
    for dets, tod, fl in groups:
        for det, p, f in zip(dets, tod, fl):
            assert np.array_equal(np.isfinite(p), (f & UNUSABLE) == 0), det
            ok = f == 0
            if kinds[parse_detector_id(det)[2]] == CHANNEL_SATURATED:
                assert np.all(f & SATURATED), det
                continue
            assert ok.mean() >= 0.9, (det, np.unique(f, return_counts=True))
            # its loading, shifted by the bath offset, which lies between those of OCS's coldest and warmest reading
            t = truth[det]
            shift = t.k_w_per_k_n * (t.t_bath_k**t.n - np.array([t_ocs.max(), t_ocs.min()]) ** t.n)
            low, high = t.p_opt_w + shift - 0.02 * t.p_opt_w
            assert low < np.median(p[ok]) < high + 0.04 * t.p_opt_w, (det, low, np.median(p[ok]), high)
    assert not any(np.any(fl & (HK_MISSING | HK_STALE)) for fl in flags), "samples without a fresh OCS reading"

"""G3 ingest and egress (issue 13): fixtures built at test time with spt3g's own classes.

A run of 2 modules x 4 channels is written as raw DAQ frames (Wiring,
Housekeeping, GcpSlow, Timepoints with DfMux samples) and, through spt3g's
own FixedLengthScans + DfMuxCollator + G3Writer, as collated Scan frames.
"""

from __future__ import annotations

import numpy as np
import pytest

spt3g_core = pytest.importorskip("spt3g.core")

from mntes_stream.core import flags as fl  # noqa: E402
from mntes_stream.core.timing import DFMUX_TICKS_PER_SAMPLE, G3_TICK_NS  # noqa: E402
from mntes_stream.g3 import frames as F  # noqa: E402
from mntes_stream.g3 import spt3g  # noqa: E402
from mntes_stream.g3.mapping import Wiring  # noqa: E402
from mntes_stream.g3.settings import G3InputConfig  # noqa: E402

T0_NS = 1_700_000_000 * 10**9
SAMPLE_NS = DFMUX_TICKS_PER_SAMPLE * G3_TICK_NS
BOARD = 1234
MODULES = (2, 5)   # wiring-map module numbers (0-7): one on each mezzanine
N_CH = 4
N_SAMP = 60
LAYOUT = {f"W{m}.{c}": (BOARD, m, c) for m in MODULES for c in range(N_CH)}


def module_hk(nuller_gain=2):
    return {m: F.ModuleHk(nuller_gain, 3, 0.05 + 0.01 * np.arange(N_CH), 1.6e6 + 1e5 * np.arange(N_CH) + 1e4 * m)
            for m in MODULES}


def true_counts(k):
    """Counts of sample k, per (module, channel): I, Q (int)."""
    rng = np.random.default_rng(k)
    return {m: (rng.integers(-500_000, 500_000, N_CH), rng.integers(-500_000, 500_000, N_CH)) for m in MODULES}


def raw_frames(n=N_SAMP, hk_change_at=None, scale_after=1.0, nan_at=None, bath=True):
    """Raw DAQ frames; optionally the nuller gain changes at sample ``hk_change_at`` (housekeeping
    frame written at the END of the file: not in time order with the data) with counts scaled by
    ``scale_after`` from that sample on."""
    out = [F.wiring_frame(LAYOUT), F.housekeeping_frame(T0_NS - SAMPLE_NS, {BOARD: module_hk(2)})]
    if bath:
        out.append(F.gcpslow_frame(T0_NS, 0.1))
    for k in range(n):
        c = true_counts(k)
        if hk_change_at is not None and k >= hk_change_at:
            c = {m: (np.rint(i * scale_after[m]), np.rint(q * scale_after[m])) for m, (i, q) in c.items()}
        out.append(F.timepoint_frame(T0_NS + k * SAMPLE_NS, {(BOARD, m): c[m] for m in MODULES}, N_CH))
        if bath and k % 20 == 19:
            out.append(F.gcpslow_frame(T0_NS + k * SAMPLE_NS, 0.1 + 1e-4 * k / N_SAMP))
    if hk_change_at is not None:
        out.append(F.housekeeping_frame(T0_NS + hk_change_at * SAMPLE_NS, {BOARD: module_hk(7)}))
    return out


def write(frames, path, collate=False, scan_len=25):
    core, dfmux = spt3g()
    it = iter(frames)
    pipe = core.G3Pipeline()
    state = {"done": False}

    def source(frame):
        if state["done"]:
            return []
        try:
            return [next(it)]
        except StopIteration:
            state["done"] = True
            return []

    pipe.Add(source)
    if collate:
        pipe.Add(dfmux.FixedLengthScans, N=scan_len)
        pipe.Add(dfmux.DfMuxCollator, flac_compress=True)
    pipe.Add(core.G3Writer, filename=str(path))
    pipe.Run()
    return path


@pytest.fixture(scope="module")
def run_files(tmp_path_factory):
    d = tmp_path_factory.mktemp("g3run")
    raw = write(raw_frames(), d / "raw.g3")
    scans = write(raw_frames(), d / "scans.g3", collate=True)
    return raw, scans


def messages_by_detector(path, chunk_samples=16):
    from mntes_stream.g3.files import g3_messages
    from mntes_stream.io.messages import decode

    counts, bias = {}, {}
    for _, key, payload in g3_messages(path, "lab", chunk_samples=chunk_samples):
        msg = decode(payload)
        if "/counts/" in key:
            for row, ch in enumerate(msg.channels):
                d = f"b{msg.board}m{msg.module}c{ch:03d}"
                for t, i, q in zip(msg.times_ns(), msg.counts_i[row], msg.counts_q[row]):
                    counts[(d, int(t))] = (int(i), int(q))
        elif "/bias/" in key:
            for row, ch in enumerate(msg.channels):
                bias[(msg.board, msg.module, int(ch), int(msg.t_ns[0]))] = float(msg.value[0, row])
    return counts, bias


def test_wiring_both_ways(run_files):
    raw, _ = run_files
    core, _ = spt3g()
    w = Wiring.from_frame(next(iter(core.G3File(str(raw)))))
    assert w.id_of("W5.3") == "b1234m5c003"
    assert w.name_of("b1234m2c000") == "W2.0"
    assert all(w.name_of(w.id_of(n)) == n for n in LAYOUT)


def test_both_layouts_give_the_same_counts_and_times(run_files):
    raw, scans = run_files
    c_raw, bias_raw = messages_by_detector(raw)
    c_scan, bias_scan = messages_by_detector(scans)
    assert len(c_raw) == len(LAYOUT) * N_SAMP
    assert c_raw == c_scan
    # Times are the G3 ticks x 10 ns, the exact DfMux rate.
    times = sorted({t for (_, t) in c_raw})
    assert times == [T0_NS + k * SAMPLE_NS for k in range(N_SAMP)]
    # Sample 7 of W5.1 is what the Timepoint frame said (I, Q interleaved, wiring channel 0-indexed).
    i7, q7 = true_counts(7)[5]
    assert c_raw[("b1234m5c001", T0_NS + 7 * SAMPLE_NS)] == (int(i7[1]), int(q7[1]))
    # Bias: spt3g's own bolo_bias_voltage_rms of the housekeeping (1-indexed tree, 0-indexed wiring).
    from spt3g.dfmux.unittransforms import bolo_bias_voltage_rms

    hk = F.housekeeping_frame(T0_NS - SAMPLE_NS, {BOARD: module_hk(2)})["DfMuxHousekeeping"]
    w = Wiring.from_frame(F.wiring_frame(LAYOUT))
    v = bolo_bias_voltage_rms(w.wiring_map, hk, "W5.2", "ICE", "spt3g_filtering_2017_full")
    assert bias_raw[(BOARD, 5, 2, T0_NS - SAMPLE_NS)] == v
    assert bias_raw == bias_scan


def _convert_spt3g_power(path):
    """spt3g's own ConvertTimestreamUnits(Power) of RawTimestreams_I, per bolometer (concatenated scans)."""
    core, dfmux = spt3g()
    out: dict = {}
    pipe = core.G3Pipeline()
    pipe.Add(core.G3Reader, filename=str(path))
    pipe.Add(dfmux.ConvertTimestreamUnits, Input="RawTimestreams_I", Output="PowerTS",
             Units=core.G3TimestreamUnits.Power)

    def grab(frame):
        if frame.type == core.G3FrameType.Scan and "PowerTS" in frame:
            for k, ts in frame["PowerTS"].items():
                out.setdefault(k, []).append(np.asarray(ts, dtype=float))

    pipe.Add(grab)
    pipe.Run()
    return {k: np.concatenate(v) for k, v in out.items()}


def _optical(path, **kw):
    core, _ = spt3g()
    out, flags = {}, {}
    for frame in core.G3File(str(path)):
        if frame.type == core.G3FrameType.Scan and "MntesOpticalPower" in frame:
            for k, ts in frame["MntesOpticalPower"].items():
                out.setdefault(k, []).append(np.asarray(ts))
                flags.setdefault(k, []).append(np.asarray(frame["MntesFlags"][k]))
    return {k: np.concatenate(v) for k, v in out.items()}, {k: np.concatenate(v) for k, v in flags.items()}


def test_electrical_matches_spt3g_convert_timestream_units(run_files, tmp_path):
    from mntes_stream.g3.files import g3_to_g3

    _, scans = run_files
    ref = _convert_spt3g_power(scans)
    res = g3_to_g3(scans, tmp_path / "el.g3", kind="electrical")
    assert res["scans"] == 3
    p, f = _optical(tmp_path / "el.g3")
    assert set(p) == set(LAYOUT) == set(ref)
    for name in LAYOUT:
        assert p[name].dtype == np.float64
        assert not f[name].any()
        # Optical = constant - electrical; without parameters the constant is 0.
        np.testing.assert_allclose(-p[name], ref[name], rtol=2**-23, atol=0)


def test_gain_change_mid_run_applies_at_its_sample(tmp_path):
    """The nuller gain changes at sample 37 (its housekeeping frame written last, out of time order);
    the counts scale by the inverse ratio of amps per count, so the true current, hence power, is unchanged."""
    from mntes_stream.g3.files import g3_to_g3
    from mntes_stream.g3.mapping import hk_snapshot

    w = Wiring.from_frame(F.wiring_frame(LAYOUT))
    a2 = hk_snapshot(F.housekeeping_frame(T0_NS, {BOARD: module_hk(2)})["DfMuxHousekeeping"], w).amps_rms_per_count
    a7 = hk_snapshot(F.housekeeping_frame(T0_NS, {BOARD: module_hk(7)})["DfMuxHousekeeping"], w).amps_rms_per_count
    scale = {m: np.array([a2[w.index_of_names([f"W{m}.{c}"])[0]] / a7[w.index_of_names([f"W{m}.{c}"])[0]]
                          for c in range(N_CH)]) for m in MODULES}
    change = 37
    base = write(raw_frames(), tmp_path / "base.g3", collate=True)
    changed = write(raw_frames(hk_change_at=change, scale_after=scale), tmp_path / "chg.g3", collate=True)
    g3_to_g3(base, tmp_path / "base_p.g3", kind="electrical")
    res = g3_to_g3(changed, tmp_path / "chg_p.g3", kind="electrical")
    assert res["housekeeping_changes"] == 1
    p0, _ = _optical(tmp_path / "base_p.g3")
    p1, _ = _optical(tmp_path / "chg_p.g3")
    for k, name in enumerate(w.names):
        ratio = p1[name] / p0[name]
        np.testing.assert_array_equal(ratio[:change], 1.0)
        # From sample 37 on the new gain: equal up to rounding the scaled counts to integers
        # (half a count); one sample early or late would be off by the gain ratio (> 20 %).
        np.testing.assert_allclose(ratio[change:], 1.0, rtol=1e-2)
        assert abs(a7[k] / a2[k] - 1) > 0.2


def test_nan_and_beyond_24_bits_are_flagged(tmp_path):
    from mntes_stream.g3.files import g3_to_g3

    frames = raw_frames()
    core, dfmux = spt3g()
    # Sample 3 of W2.1 beyond 24 bits (a raw DfMux word can hold it; FLAC cannot).
    tp = [f for f in frames if f.type == core.G3FrameType.Timepoint][3]
    np.asarray(tp["DfMux"][BOARD][2])[2] = 2**23 + 5
    path = write(frames, tmp_path / "edge.g3")
    g3_to_g3(path, tmp_path / "edge_p.g3", kind="electrical")
    p, f = _optical(tmp_path / "edge_p.g3")
    assert f["W2.1"][3] & fl.INVALID_INPUT and np.isnan(p["W2.1"][3])
    assert np.count_nonzero(np.concatenate(list(f.values()))) == 1


def test_missing_bath_source_is_a_clear_error(tmp_path):
    from mntes_stream.core.params import table1_params
    from mntes_stream.errors import ConfigError
    from mntes_stream.g3.files import g3_to_g3

    path = write(raw_frames(bath=False), tmp_path / "nobath.g3", collate=True)
    params = {n: table1_params(n) for n in LAYOUT}
    with pytest.raises(ConfigError, match="no bath temperature"):
        g3_to_g3(path, tmp_path / "x.g3", params=params, kind="exact")
    # A default makes it convert; kinds that ignore the bath need neither.
    assert g3_to_g3(path, tmp_path / "d.g3", params=params, kind="exact",
                    config=G3InputConfig(t_bath_default_k=0.1))["detector_samples"] == len(LAYOUT) * N_SAMP
    for kind, p in (("electrical", None), ("electrical", params), ("linear", params)):
        assert g3_to_g3(path, tmp_path / f"{kind}{p is None}.g3", params=p, kind=kind)["scans"] == 3


SPT3G_1_0_2 = r"""
import sys
sys.modules["so3g"] = None   # no so3g/toast in this process: spt3g is the installed spt3g 1.0.2 itself
sys.modules["toast"] = None  # (so3g replaces sys.modules['spt3g'] with its bundled copy when imported)
sys.path.insert(0, sys.argv[1])
import numpy as np
import spt3g, spt3g.core
assert "so3g" not in spt3g.core.__file__, spt3g.core.__file__
from spt3g import version
import test_g3 as t
from mntes_stream.g3.files import g3_to_g3
from pathlib import Path
d = Path(sys.argv[2])
scans = t.write(t.raw_frames(), d / "scans.g3", collate=True)
ref = t._convert_spt3g_power(scans)
g3_to_g3(scans, d / "el.g3", kind="electrical")
p, f = t._optical(d / "el.g3")
for name in t.LAYOUT:
    np.testing.assert_allclose(-p[name], ref[name], rtol=2**-23, atol=0)
print(version.version)
"""


def test_electrical_matches_convert_timestream_units_of_spt3g_1_0_2_itself(tmp_path):
    """The same check with the spt3g package (1.0.2), not so3g's bundled copy that this test process
    loads (so3g and toast go first here, and so3g installs its own spt3g as ``spt3g``)."""
    import subprocess
    import sys
    from pathlib import Path

    p = subprocess.run([sys.executable, "-c", SPT3G_1_0_2, str(Path(__file__).parent), str(tmp_path)],
                       capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stderr[-3000:]
    assert p.stdout.split()[-1] == "1.0.2"


def test_bolometer_without_parameters_is_reported_once_and_skipped(run_files, tmp_path, caplog):
    import logging

    from mntes_stream.core.params import table1_params
    from mntes_stream.g3.files import g3_to_g3

    _, scans = run_files
    params = {n: table1_params(n) for n in LAYOUT if n != "W5.2"}  # keyed by bolometer name, one missing
    with caplog.at_level(logging.WARNING, logger="mntes_stream.g3"):
        res = g3_to_g3(scans, tmp_path / "p.g3", params=params, kind="exact", config=G3InputConfig())
    assert res["scans"] == 3 and res["skipped_bolometers"] == 1
    said = [r.getMessage() for r in caplog.records if "W5.2" in r.getMessage()]
    assert len(said) == 1 and "without parameters" in said[0]
    p, _ = _optical(tmp_path / "p.g3")
    assert set(p) == set(LAYOUT) - {"W5.2"}


def test_cli_convert_and_export_take_g3_runs(run_files, tmp_path, capsys):
    import json

    import h5py

    from mntes_stream.cli import main
    from mntes_stream.core.params import table1_params
    from mntes_stream.io.mcap import Session
    from mntes_stream.io.paramfile import dump_params

    raw, scans = run_files
    dump_params([table1_params(n) for n in LAYOUT], tmp_path / "names.toml")  # keyed by bolometer name
    assert main(["convert", str(raw), str(tmp_path / "el.g3"), "--kind", "electrical", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["detector_samples"] == len(LAYOUT) * N_SAMP
    assert main(["convert", str(raw), str(tmp_path / "out.mcap"), "--params", str(tmp_path / "names.toml"),
                 "-q", "--json"]) == 0
    capsys.readouterr()
    topics = Session(tmp_path / "out.mcap").message_counts()
    assert {f"mntes/lab/power/{BOARD}/{m}" for m in MODULES} <= set(topics)
    assert topics[f"mntes/lab/counts/{BOARD}/2"] == topics[f"mntes/lab/power/{BOARD}/2"] == 4  # 60 samples / 16
    assert main(["export", str(scans), "--out", str(tmp_path / "x.h5"), "--g3-params", str(tmp_path / "names.toml"),
                 "--json"]) == 0
    with h5py.File(tmp_path / "x.h5") as h:
        assert {f"lab_b{BOARD}m{m}" for m in MODULES} <= set(h)
        assert h[f"lab_b{BOARD}m5"]["tod"].shape == (N_CH, N_SAMP)
    assert main(["convert", str(raw), str(tmp_path / "y.g3")]) == 2  # table kind needs parameters: one line
    assert "needs detector parameters" in capsys.readouterr().err


def test_run_without_thermometer_needs_a_default(tmp_path):
    from mntes_stream.errors import ConfigError
    from mntes_stream.g3.files import g3_messages

    path = write(raw_frames(bath=False), tmp_path / "nobath.g3")
    with pytest.raises(ConfigError, match="t_bath_default_k"):
        list(g3_messages(path, "lab"))
    msgs = list(g3_messages(path, "lab", G3InputConfig(t_bath_default_k=0.08)))
    baths = [p for _, k, p in msgs if k == "mntes/lab/hk/t_bath"]
    chunk_times = {t for t, k, _ in msgs if "/counts/" in k}
    assert len(baths) == len(chunk_times) == 4  # a default reading with every chunk time (60 samples / 16)


def test_bridges_split_by_board_cover_the_array_once(tmp_path):
    from mntes_stream.bench.g3 import write_run
    from mntes_stream.g3.files import read_frames
    from mntes_stream.g3.translate import FrameTranslator

    path = tmp_path / "two_boards.g3"
    total = write_run(path, boards=2, modules=2, channels=4, n_samples=20)
    seen = {}
    for boards in ((), (0,), (1,)):
        tr = FrameTranslator("lab", chunk_samples=8, boards=boards)
        keys_ = {k for f in read_frames(path) for k, _ in tr.handle(f)} | {k for k, _ in tr.flush()}
        seen[boards] = (tr.counters.samples, {k for k in keys_ if "/counts/" in k})
    assert seen[()][0] == total == seen[(0,)][0] + seen[(1,)][0]
    assert seen[(0,)][1] == {"mntes/lab/counts/0/0", "mntes/lab/counts/0/1"}
    assert seen[(0,)][1] | seen[(1,)][1] == seen[()][1] and not seen[(0,)][1] & seen[(1,)][1]


def test_bad_g3_input_is_one_line(run_files, tmp_path, capfd):
    from mntes_stream.cli import main

    raw, _ = run_files
    (tmp_path / "bad.g3").write_bytes(b"not a G3 file")
    (tmp_path / "cut.g3").write_bytes(raw.read_bytes()[:3000])
    for name in ("bad.g3", "cut.g3", "absent.g3"):
        assert main(["convert", str(tmp_path / name), str(tmp_path / "o.g3"), "--kind", "electrical"]) == 2
        err = capfd.readouterr().err.strip().splitlines()
        assert len(err) == 1 and name in err[0], err
    assert not (tmp_path / "o.g3").exists()


def test_repeated_housekeeping_reuses_spt3g_values_and_a_change_recomputes():
    from spt3g.dfmux.unittransforms import counts_to_rms_amps

    from mntes_stream.g3.mapping import hk_snapshot

    w = Wiring.from_frame(F.wiring_frame(LAYOUT))
    first = hk_snapshot(F.housekeeping_frame(T0_NS, {BOARD: module_hk(2)})["DfMuxHousekeeping"], w)
    again = hk_snapshot(F.housekeeping_frame(T0_NS + 10**9, {BOARD: module_hk(2)})["DfMuxHousekeeping"], w,
                        previous=first)
    assert again.amps_rms_per_count is first.amps_rms_per_count and again.t_ns == T0_NS + 10**9
    hk7 = F.housekeeping_frame(T0_NS + 2 * 10**9, {BOARD: module_hk(7)})["DfMuxHousekeeping"]
    changed = hk_snapshot(hk7, w, previous=first)
    k = w.index_of_names(["W5.3"])[0]
    assert changed.amps_rms_per_count[k] == counts_to_rms_amps(w.wiring_map, hk7, "W5.3", "ICE",
                                                               "spt3g_filtering_2017_full")
    assert changed.amps_rms_per_count[k] != first.amps_rms_per_count[k]


def test_optical_power_in_a_users_own_g3_pipeline(run_files, tmp_path):
    """What an SPT-3G user writes: the module added after the collator in their own G3Pipeline."""
    import mntes_stream.g3
    from mntes_stream.g3.files import g3_to_g3

    core, dfmux = spt3g()
    raw, _ = run_files
    pipe = core.G3Pipeline()
    pipe.Add(core.G3Reader, filename=str(raw))
    pipe.Add(dfmux.FixedLengthScans, N=25)
    pipe.Add(dfmux.DfMuxCollator)
    pipe.Add(mntes_stream.g3.OpticalPower, kind="electrical")
    pipe.Add(core.G3Writer, filename=str(tmp_path / "user.g3"))
    pipe.Run()
    g3_to_g3(raw, tmp_path / "cli.g3", kind="electrical", scan_samples=25)
    mine, flags = _optical(tmp_path / "user.g3")
    ref, _ = _optical(tmp_path / "cli.g3")
    assert set(mine) == set(LAYOUT)
    for name in LAYOUT:
        np.testing.assert_array_equal(mine[name], ref[name])
        assert mine[name].size == N_SAMP and not flags[name].any()
    kinds = [str(f.type) for f in core.G3File(str(tmp_path / "user.g3"))]
    assert kinds.count("Scan") == 3 and "Wiring" in kinds and "Housekeeping" in kinds  # everything else passes

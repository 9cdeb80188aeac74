"""Mapmaking frameworks load our power natively: each framework's own loader reads ``export --format <it>``.

One recording (real MCAP, written with the recorder's writer): two modules,
missing chunks (NaN + GAP), a detector that comes and goes (NaN +
UNKNOWN_CHANNEL), saturated samples, a flag that keeps its value
(HK_STALE), and a pause beyond ``max_gap_s`` (a segment break). The
reference is what ``RecordedPower`` reads, cut at the segment starts the
assembler reported. Signal is compared bit for bit (NaN included).
"""

from __future__ import annotations

import json
import sys

import h5py
import numpy as np
import pytest
from test_feeds import STEP, T0, N, bits, chunk, write

from mntes_stream.cli import main as cli_main
from mntes_stream.core import flags as fl
from mntes_stream.errors import ConfigError
from mntes_stream.feeds import RecordedPower, TodBlock

toast = pytest.importorskip("toast")
sotodlib_core = pytest.importorskip("sotodlib.core")
lbs = pytest.importorskip("litebird_sim")

from mntes_stream.feeds import frameworks as fw  # noqa: E402

RATE = 100.0
BREAK_NS = 2 * 3600 * 10**9  # beyond the default max_gap_s (1 h): a segment break


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    """``(path, expected)``: the recording and ``{observation name: TodBlock}`` as the frameworks should hold it."""
    path = tmp_path_factory.mktemp("fw") / "rec.mcap"
    sent = [chunk(s, 0) for s in range(10) if s not in (3, 4)]
    sent += [chunk(s, 0, t0_ns=T0 + s * STEP + BREAK_NS) for s in range(10, 14)]  # after a 2 h pause
    sent += [chunk(s, 1, channels=(0, 1, 2) if s % 3 else (0, 2, 5)) for s in range(8)]
    write(path, sent)
    rec = RecordedPower(path)
    expected = {}
    for sid, block in zip(rec.streams, rec.read().values()):
        cuts = [0, *rec.stats[sid].segment_starts, block.n_samples]
        for k, (a, z) in enumerate(zip(cuts[:-1], cuts[1:])):
            name = sid.name if len(cuts) == 2 else f"{sid.name}_seg{k}"
            expected[name] = TodBlock(block.setup, block.board, block.module, block.detectors, block.channels,
                                      block.t_ns[a:z], block.p_opt_w[:, a:z], block.flags[:, a:z], a)
    assert sorted(expected) == ["t_b0m0_seg0", "t_b0m0_seg1", "t_b0m1"]
    b = expected["t_b0m0_seg0"]
    assert np.any(b.flags & fl.GAP) and np.any(b.flags & fl.HK_STALE)
    assert np.any(expected["t_b0m1"].flags == fl.UNKNOWN_CHANNEL)
    return path, expected


def _export(path, fmt, out, *extra):
    assert cli_main(["export", str(path), "--format", fmt, "--out", str(out), "--json", *extra]) == 0


# ---------------------------------------------------------------- TOAST


def check_toast(obs, b: TodBlock, name: str):
    assert obs.name == name and tuple(obs.all_detectors) == b.detectors and obs.n_all_samples == b.n_samples
    np.testing.assert_array_equal(bits(obs.detdata["signal"][:]), bits(b.p_opt_w))
    assert str(obs.detdata["signal"].units) == "W"
    np.testing.assert_array_equal(obs.shared["times"].data, b.t_ns / 1e9)  # float64 s, as TOAST keeps time
    invalid = ((b.flags & fl.UNUSABLE) != 0) | np.isnan(b.p_opt_w)
    np.testing.assert_array_equal(obs.detdata["flags"][:], invalid.astype(np.uint8))  # bit 1 only: TOAST's invalid
    np.testing.assert_array_equal(obs.detdata["mntes_flags"][:], b.flags)
    gap = np.all(b.flags & fl.GAP, axis=0)
    np.testing.assert_array_equal(obs.shared["flags"].data, gap.astype(np.uint8))
    dead = {d for d, row in zip(b.detectors, invalid) if row.all()}
    assert {d for d, v in obs.local_detector_flags.items() if v & 1} == dead
    fp = obs.telescope.focalplane
    assert fp.sample_rate.to_value("Hz") == RATE and list(fp.detector_data["name"]) == list(b.detectors)
    meta = obs["mntes_stream"]
    assert meta["signal_units"] == "W" and int(meta["t_start_ns"]) == int(b.t_ns[0])
    assert bool(meta["focal_plane_placeholder"]) and float(meta["sample_rate_hz"]) == RATE


def test_toast_loader_reads_the_export_and_the_in_memory_object_equals_it(session, tmp_path):
    from toast.io import load_hdf5

    path, expected = session
    _export(path, "toast", tmp_path / "toast")
    assert sorted(p.name for p in (tmp_path / "toast").iterdir()) == [f"{n}.h5" for n in sorted(expected)]
    for name, b in expected.items():
        check_toast(load_hdf5(str(tmp_path / "toast" / f"{name}.h5"), toast.Comm(world=None)), b, name)
    objs = RecordedPower(path).to_framework("toast")
    assert [o.name for o in objs] == list(expected)
    for o, (name, b) in zip(objs, expected.items()):
        check_toast(o, b, name)


# ---------------------------------------------------------------- sotodlib


def check_axismanager(am, b: TodBlock, name: str):
    assert tuple(am.dets.vals) == b.detectors and am.samps.count == b.n_samples and am.samps.offset == b.first_sample
    np.testing.assert_array_equal(bits(am.signal), bits(b.p_opt_w))
    np.testing.assert_array_equal(am.timestamps, b.t_ns / 1e9)
    assert isinstance(am.flags, sotodlib_core.FlagManager)
    for bit, flag in fl.NAMES.items():
        np.testing.assert_array_equal(am.flags[flag].mask(), (b.flags & bit) != 0, err_msg=flag)
    np.testing.assert_array_equal(am.flags["unusable"].mask(), (b.flags & fl.UNUSABLE) != 0)
    assert am.mntes_stream.observation == name and am.mntes_stream.signal_units == "W"
    assert am.mntes_stream.sample_rate_hz == RATE and am.mntes_stream.t_start_ns == int(b.t_ns[0])
    np.testing.assert_array_equal(am.focal_plane.xi, 0.0)
    assert bool(am.mntes_stream.focal_plane_placeholder)


def test_sotodlib_loader_reads_the_export_and_the_in_memory_object_equals_it(session, tmp_path):
    path, expected = session
    out = tmp_path / "so.h5"
    _export(path, "sotodlib", out)
    with h5py.File(out, "r") as f:
        assert json.loads(f.attrs["observations"]) == list(expected)
    for name, b in expected.items():
        check_axismanager(sotodlib_core.AxisManager.load(str(out), name), b, name)
    objs = RecordedPower(path).to_framework("sotodlib")
    for o, (name, b) in zip(objs, expected.items(), strict=True):
        check_axismanager(o, b, name)


def test_a_selection_exports_only_what_it_selects(session, tmp_path):
    path, _ = session
    sel = ["--detectors", "b0m1c005,b0m1c000", "--start", str(T0 + 2 * STEP), "--end", str(T0 + 6 * STEP)]
    _export(path, "sotodlib", tmp_path / "so.h5", *sel)
    ref = RecordedPower(path, detectors=["b0m1c005", "b0m1c000"], start_ns=T0 + 2 * STEP,
                        end_ns=T0 + 6 * STEP).read()["t_b0m1"]
    am = sotodlib_core.AxisManager.load(str(tmp_path / "so.h5"), "t_b0m1")
    with h5py.File(tmp_path / "so.h5", "r") as f:
        assert json.loads(f.attrs["observations"]) == ["t_b0m1"]
    check_axismanager(am, ref, "t_b0m1")
    assert tuple(am.dets.vals) == ("b0m1c005", "b0m1c000") and am.samps.count == 4 * N


# ---------------------------------------------------------------- litebird_sim


def check_litebird(obs, b: TodBlock):
    assert tuple(obs.name) == b.detectors and obs.tod.shape == (b.n_detectors, b.n_samples)
    np.testing.assert_array_equal(bits(obs.tod), bits(b.p_opt_w))
    np.testing.assert_array_equal(obs.local_flags, b.flags)
    assert obs.sampling_rate_hz == RATE
    # litebird_sim has no per-sample times: start (float s) + k / rate, within float64 resolution at 2023.
    assert np.abs(obs.get_times() - b.t_ns / 1e9).max() < 1e-6


def test_litebird_loader_reads_the_export_and_the_in_memory_object_equals_it(session, tmp_path):
    path, expected = session
    out = tmp_path / "lbs"
    _export(path, "litebird_sim", out)
    files = sorted(out.glob("*.h5"))
    assert [f.stem for f in files] == sorted(expected)
    raw = lbs.read_list_of_observations(files, tod_dtype=np.float64, limit_mpi_rank=False)
    for obs, f in zip(raw, files):
        check_litebird(obs, expected[f.stem])
        with h5py.File(f, "r") as h:
            assert h["tod"].attrs["units"] == "W" and "no watt" in h["tod"].attrs["description"]
            np.testing.assert_array_equal(h["mntes_t_ns"][:], expected[f.stem].t_ns)
    ours = fw.read_litebird(out)
    for obs, f in zip(ours, files):
        assert obs.tod_list[0].units == "W" and obs.mntes_stream["signal_units"] == "W"
        np.testing.assert_array_equal(obs.mntes_t_ns, expected[f.stem].t_ns)
    objs = RecordedPower(path).to_framework("litebird_sim")
    for o, (name, b) in zip(objs, expected.items(), strict=True):
        check_litebird(o, b)
        assert o.mntes_stream["observation"] == name and o.tod_list[0].units == "W"


def test_litebird_refuses_times_off_the_even_grid(session):
    _, expected = session
    b = expected["t_b0m1"]
    t = np.array(b.t_ns)
    t[5:] += 3000  # a 3 us step: litebird_sim could only place these samples 3 us off
    jittered = TodBlock(b.setup, b.board, b.module, b.detectors, b.channels, t, b.p_opt_w, b.flags)
    with pytest.raises(ConfigError, match="stray 3000 ns"):
        fw.to_litebird(jittered, sample_rate_hz=RATE)


def test_the_framework_quirks_the_readme_states(session, tmp_path):
    """What the README says the frameworks do on their own (the workarounds depend on it; a new version may not)."""
    from dataclasses import asdict

    import astropy.units as u

    b = session[1]["t_b0m1"]
    # TOAST's noise model takes only K^2 s: NoiseEstim's out_model cannot hold spectra of power.
    with pytest.raises(ValueError, match="K\\*\\*2"):
        toast.noise.Noise(detectors=["d"], freqs={"d": np.arange(1.0, 4.0) * u.Hz},
                          psds={"d": np.ones(3) * u.W**2 * u.s}, indices={"d": 0})
    # litebird_sim: its loader labels units it does not know (W) K_CMB.
    obs = fw.to_litebird(b, sample_rate_hz=RATE)
    (f,) = lbs.write_list_of_observations(obs, tmp_path, tod_dtype=np.float64, tod_fields=["tod"])
    assert lbs.read_list_of_observations([f], tod_dtype=np.float64, limit_mpi_rank=False)[0].tod_list[0].units \
        == lbs.Units.K_CMB
    # ... global_flags come back run-length encoded, not as written;
    obs.global_flags = np.arange(b.n_samples, dtype=np.uint16) % 3
    (tmp_path / "g").mkdir()
    (f,) = lbs.write_list_of_observations(obs, tmp_path / "g", tod_dtype=np.float64, tod_fields=["tod"])
    back = lbs.read_list_of_observations([f], tod_dtype=np.float64, limit_mpi_rank=False)[0].global_flags
    assert back.shape != obs.global_flags.shape or not np.array_equal(back, obs.global_flags)
    # ... a file without a pointing provider, or a detector without a band centre, does not load.
    for bare in ("pointing", "band"):
        o = fw.to_litebird(b, sample_rate_hz=RATE)
        if bare == "pointing":
            o.pointing_provider = None
        else:
            dets = [asdict(lbs.DetectorInfo(name=d, sampling_rate_hz=RATE)) for d in b.detectors]
            o = lbs.Observation(detectors=dets, n_samples_global=b.n_samples, start_time_global=0.0,
                                sampling_rate_hz=RATE)
            o.pointing_provider = obs.pointing_provider
        (tmp_path / bare).mkdir()
        (f,) = lbs.write_list_of_observations(o, tmp_path / bare, tod_fields=["tod"])
        with pytest.raises((KeyError, ValueError)):
            lbs.read_list_of_observations([f], limit_mpi_rank=False)


# ---------------------------------------------------------------- shared behaviour


def test_positions_reach_each_focal_plane(session):
    from toast.instrument_coords import xieta_to_quat

    b = session[1]["t_b0m1"]
    pos = {d: (0.01 * i, -0.02 * i, 0.3 * i) for i, d in enumerate(b.detectors)}
    xi, eta, gamma = (np.array([pos[d][k] for d in b.detectors]) for k in range(3))
    obs = fw.to_toast(b, positions=pos)
    np.testing.assert_allclose(np.array(obs.telescope.focalplane.detector_data["quat"]),
                               xieta_to_quat(xi, eta, gamma), atol=1e-15)
    assert not obs["mntes_stream"]["focal_plane_placeholder"]
    am = fw.to_axismanager(b, positions=pos)
    np.testing.assert_array_equal(am.focal_plane.gamma, gamma)
    lb = fw.to_litebird(b, positions=pos)
    np.testing.assert_array_equal(lb.pol_angle_rad, gamma)
    with pytest.raises(ConfigError, match="no \\(xi, eta, gamma\\)"):
        fw.to_toast(b, positions={b.detectors[0]: (0, 0, 0)})


def test_export_focal_plane_csv_reaches_the_files(session, tmp_path):
    from toast.instrument_coords import xieta_to_quat
    from toast.io import load_hdf5

    path, expected = session
    dets = sorted({d for b in expected.values() for d in b.detectors})
    pos = {d: (0.001 * i, 0.002 * i, 0.1 * i) for i, d in enumerate(dets)}
    csv = tmp_path / "fp.csv"
    csv.write_text("detector,xi_rad,eta_rad,gamma_rad\n" + "".join(f"{d},{x!r},{e!r},{g!r}\n"
                                                                   for d, (x, e, g) in pos.items()))
    _export(path, "toast", tmp_path / "toast", "--focal-plane", str(csv))
    _export(path, "sotodlib", tmp_path / "so.h5", "--focal-plane", str(csv))
    b = expected["t_b0m1"]
    xi, eta, gamma = (np.array([pos[d][k] for d in b.detectors]) for k in range(3))
    fp = load_hdf5(str(tmp_path / "toast" / "t_b0m1.h5"), toast.Comm(world=None)).telescope.focalplane
    np.testing.assert_allclose(np.array(fp.detector_data["quat"]), xieta_to_quat(xi, eta, gamma), atol=1e-15)
    am = sotodlib_core.AxisManager.load(str(tmp_path / "so.h5"), "t_b0m1")
    np.testing.assert_array_equal(am.focal_plane.xi, xi)
    assert not am.mntes_stream.focal_plane_placeholder
    csv.write_text("detector,xi_rad,eta_rad,gamma_rad\nb0m0c000,0,0,nan\n")
    assert cli_main(["export", str(path), "--format", "toast", "--out", str(tmp_path / "t2"), "--focal-plane",
                     str(csv)]) == 2


def test_focal_plane_from_g3_bolometer_properties(session, tmp_path):
    pytest.importorskip("spt3g")
    from mntes_stream.g3 import spt3g
    from mntes_stream.g3.frames import wiring_frame

    core, _ = spt3g()
    from spt3g import calibration

    path, expected = session
    dets = sorted({d for b in expected.values() for d in b.detectors})
    layout = {f"bolo_{d}": (int(d[1]), int(d[3]), int(d[5:])) for d in dets}  # b<board>m<module>c<channel>
    cal = core.G3Frame(core.G3FrameType.Calibration)
    props = calibration.BolometerPropertiesMap()
    for i, name in enumerate(layout):
        p = calibration.BolometerProperties()
        p.x_offset, p.y_offset = 0.1 * i * core.G3Units.deg, -0.05 * i * core.G3Units.arcmin
        p.pol_angle = 7.5 * i * core.G3Units.deg
        props[name] = p
    cal["BolometerProperties"] = props
    run = tmp_path / "cal.g3"
    w = core.G3Writer(str(run))
    w(wiring_frame(layout))
    w(cal)
    w(core.G3Frame(core.G3FrameType.EndProcessing))
    del w
    _export(path, "sotodlib", tmp_path / "so.h5", "--focal-plane", str(run))
    b = expected["t_b0m1"]
    am = sotodlib_core.AxisManager.load(str(tmp_path / "so.h5"), "t_b0m1")
    i = np.array([dets.index(d) for d in b.detectors])
    np.testing.assert_allclose(am.focal_plane.xi, np.deg2rad(0.1 * i), rtol=1e-12)
    np.testing.assert_allclose(am.focal_plane.eta, -np.deg2rad(0.05 * i / 60), rtol=1e-12)
    np.testing.assert_allclose(am.focal_plane.gamma, np.deg2rad(7.5 * i), rtol=1e-12)
    assert "BolometerProperties" in am.mntes_stream.focal_plane and not am.mntes_stream.focal_plane_placeholder


def test_a_block_across_a_segment_break_is_refused_and_segments_split_it(session):
    path, expected = session
    whole = RecordedPower(path, module=0).read()["t_b0m0"]
    for convert in (fw.to_toast, fw.to_axismanager, fw.to_litebird):
        with pytest.raises(ConfigError, match="segment break"):
            convert(whole)
    parts = fw.segments(whole)
    assert [p.n_samples for p in parts] == [expected["t_b0m0_seg0"].n_samples, expected["t_b0m0_seg1"].n_samples]


@pytest.mark.parametrize("fmt, module, extra", [("toast", "toast", "toast"), ("sotodlib", "sotodlib.core", "sotodlib"),
                                                ("litebird_sim", "litebird_sim", "litebird")])
def test_a_missing_framework_is_one_line_naming_its_extra(session, tmp_path, monkeypatch, capsys, fmt, module, extra):
    monkeypatch.setitem(sys.modules, module, None)  # what `import` sees when the package is not installed
    assert cli_main(["export", str(session[0]), "--format", fmt, "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and f"pip install 'mntes-stream[{extra}]'" in err
    assert not (tmp_path / "x").exists()


def test_live_feed_hands_out_framework_objects_equal_to_what_was_published(tmp_path):
    from test_feeds_live import _Publisher

    from mntes_stream.feeds import LivePowerFeed
    from mntes_stream.io import keys
    from mntes_stream.io.transport import free_tcp_port, loopback

    port = free_tcp_port()
    sent = [chunk(s, 0) for s in (0, 1, 3, 4)]  # seq 2 lost: NaN + GAP in the object
    feed = LivePowerFeed(loopback(listen_port=port), "t", idle_timeout_s=1.5, duration_s=60)
    pub = _Publisher(port, [(keys.power_key("t", 0, 0), c.to_bytes()) for c in sent], [keys.power_key("t", 0, 0)])
    with feed:
        pub.start()
        try:
            (am,) = feed.to_framework("sotodlib")
        finally:
            pub.done.set()
            pub.join(30)
    assert pub.error is None, pub.error
    ref = RecordedPower(write(tmp_path / "same.mcap", sent)).read()["t_b0m0"]  # the same chunks, recorded
    check_axismanager(am, ref, "t_b0m0")
    assert np.all(am.flags.gap.mask()[:, 2 * N:3 * N])



def test_a_g3_run_exports_to_a_framework_in_one_fresh_process(tmp_path):
    """G3 input loads spt3g, the export then a framework: in a new process, in that order, without a crash."""
    import subprocess

    pytest.importorskip("spt3g")
    run = tmp_path / "run.g3"
    sim = subprocess.run([sys.executable, "-m", "mntes_stream", "simulate", "--format", "g3", "--out", str(run),
                          "--duration", "1", "--modules", "1", "--channels", "4"], capture_output=True, text=True,
                         timeout=300)
    assert sim.returncode == 0, sim.stderr[-2000:]
    out = tmp_path / "so.h5"
    res = subprocess.run([sys.executable, "-m", "mntes_stream", "export", str(run), "--g3-params",
                          str(tmp_path / "run.params.toml"), "--format", "sotodlib", "--out", str(out), "--json"],
                         capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-2000:]
    (name,) = json.loads(res.stdout)["observations"]
    am = sotodlib_core.AxisManager.load(str(out), name)
    assert am.dets.count == 4 and am.samps.count > 100 and np.isfinite(am.signal).any()

"""dfmux-bridge reads the boards' own housekeeping (tuber ``Dfmux._dump_housekeeping``, as spt3g does).

The end-to-end test runs, in a private network and mount namespace
(``unshare -n -m``: loopback up, ``/etc/hosts`` bind-mounted so that
``iceboard0010.local`` is 127.0.0.1), a stand-in board's tuber on port 80
(``python -m mntes_stream.dfmux.standin``), a zenoh router, the bridge, a
converter and a recorder (each its own process, zenoh on 127.0.0.1) while
the synthetic sender's packets flow; mid-run the stand-in retunes one
module (carrier amplitude x 0.9), latches a channel, rails a module's
carrier, and then stops answering. The recording shows what each change did.
"""

from __future__ import annotations

import importlib.util
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from test_dfmux_bridge import netns  # noqa: F401 - the fixture: spt3g and a private network namespace

SERIAL = 10
DURATION_S = 9.0
HK_EVERY_S, HK_STALE_S = 0.4, 1.5
CHANNELS = 16  # per module, as the sender sends them


def test_board_hosts_and_tracker_are_checked():
    """``SERIAL=HOST[:PORT]`` parsed, a bad one a one-line ConfigError; stand-in states map to flags."""
    from mntes_stream.dfmux.boardhk import parse_hosts
    from mntes_stream.errors import ConfigError

    assert parse_hosts(["10=127.0.0.1:8080", "11=lab-board"]) == {10: ("127.0.0.1", 8080), 11: ("lab-board", 80)}
    for bad in ("x=host", "10=", "10=host:0", "10=host:http"):
        with pytest.raises(ConfigError, match="expected SERIAL=HOST"):
            parse_hosts([bad])


def _reading(t_ns, amplitude=1.0, state="tuned", r_normal=1.0, r_frac=0.73, loop_gain=9.9):
    from mntes_stream.core import flags as fl
    from mntes_stream.dfmux.boardhk import BoardReading, ModuleReading

    ch = np.arange(4, dtype=np.int32)
    states = (state, "tuned", "overbiased", "")
    mr = ModuleReading(ch, ("Lab.a", "Lab.b", "b10m0c002", "b10m0c003"), np.full(4, 3e-6 * amplitude),
                       np.full(4, 4.5e-11), np.array([0, 0, fl.UNTUNED, fl.RAILED], dtype=fl.FLAG_DTYPE), states,
                       np.array([r_normal, 1.0, 1.0, np.nan]), np.array([r_frac, 0.73, 0.73, np.nan]),
                       np.array([loop_gain, 9.9, 9.9, np.nan]), {"carrier": 3, "nuller": 2})
    return BoardReading(10, t_ns, {0: mr}, 2)


def test_tracker_bias_steps_flags_stale_and_tuning():
    """The tracker alone (readings made by hand): the first reading publishes bias and flags; a retune is a
    step (old value 1 ns before, new at the stamp, never before a sample already published); the tuning
    check names the detector off its parameters; a failure is one event; stale flags every channel."""
    from mntes_stream.core import flags as fl
    from mntes_stream.core.params import table1_params
    from mntes_stream.dfmux.boardhk import BoardFailure, BoardHkTracker
    from mntes_stream.dfmux.publish import HkPublisher
    from mntes_stream.io.messages import decode

    pub = HkPublisher("lab", 0.1, 0.0, [(10, None, 3.3e-6)], bias_every_s=60.0)
    params = {"Lab.a": table1_params("Lab.a"), "b10m0c002": table1_params("b10m0c002")}
    tr = BoardHkTracker(pub, stale_s=2.0, bias_tolerance=0.05, params=params)
    t0 = 1_800_000_000 * 10**9
    msgs = {k: decode(v) for k, v in tr.add(_reading(t0, r_normal=2.0), t_floor_ns=t0 - 10)}
    assert set(msgs) == {"mntes/lab/hk/bias/10/0", "mntes/lab/hk/readout_flags/10/0"}
    np.testing.assert_array_equal(msgs["mntes/lab/hk/readout_flags/10/0"].value, [[0, 0, fl.UNTUNED, fl.RAILED]])
    assert tr.bias_disagree == {"10/0": {"configured_v": 3.3e-6, "board_v": 3e-6, "relative": 0.1}}
    assert set(tr.tuning_disagree) == {"b10m0c000"} and set(tr.tuning_disagree["b10m0c000"]) == {"r_normal_ohm"}
    assert sum("tuned unlike their parameters (e.g. b10m0c000: r_normal_ohm 2 on the board" in e
               for e in tr.events) == 1, tr.events
    # a retune read 1 s later, after samples up to t0 + 1.5 s were published: the step just after them
    out = [decode(v) for _, v in tr.add(_reading(t0 + 10**9, amplitude=0.9), t_floor_ns=t0 + 15 * 10**8)]
    (bias,) = out
    np.testing.assert_array_equal(bias.t_ns, [t0 + 15 * 10**8, t0 + 15 * 10**8 + 1])
    np.testing.assert_allclose(bias.value[1] / bias.value[0], 0.9)
    assert tr.tuning_disagree == {}  # R_normal agrees now
    tr.add(BoardFailure(10, "housekeeping from x:80 not read: tuber timed out"))
    tr.add(BoardFailure(10, "housekeeping from x:80 not read: tuber timed out"))
    assert sum("tuber timed out" in e for e in tr.events) == 1 and tr.status()["board_hk_failures"] == 2
    assert tr.check_stale(t0, now_wall=tr.boards[10]["t_wall"] + 1.0) == []
    (stale,) = [decode(v) for _, v in tr.check_stale(t0, now_wall=tr.boards[10]["t_wall"] + 2.5)]
    assert stale.t_ns[0] == t0 + 3 * 10**9 and np.all(stale.value.astype(int) & fl.HK_STALE)
    assert tr.check_stale(t0, now_wall=tr.boards[10]["t_wall"] + 5) == []  # said once


def _env() -> dict:
    """This checkout first on the path of a child process (spt3g 1.0.2 there, never so3g's bundled copy the
    test session loads)."""
    return dict(os.environ, PYTHONPATH=os.pathsep.join([str(Path(__file__).resolve().parents[1]),
                                                        os.environ.get("PYTHONPATH", "")]))


def _cli(*argv) -> subprocess.CompletedProcess:
    """The command in its own process."""
    return subprocess.run([sys.executable, "-m", "mntes_stream", *argv], env=_env(), capture_output=True,
                          text=True, timeout=120)


_POLL = """
import json, sys, time
from mntes_stream.dfmux.boardhk import BoardPoller
from mntes_stream.dfmux.standin import BoardState, StandInBoard

board = StandInBoard(BoardState(10), "127.0.0.1", 0)
poller = BoardPoller(10, "127.0.0.1", board.address[1], every_s=0.2, timeout_s=0.5)
poller.start()
out = [type(poller.results.get(timeout=30)).__name__]
expect = {"garbage": "answered garbage", "hang": "timed out", "ok": "BoardReading"}
for mode in sys.argv[1:]:
    board.board.apply({"mode": mode})
    # A read under way when the mode changed ends as the old mode says: the change shows within a few reads.
    for _ in range(6):
        r = poller.results.get(timeout=30)
        said = getattr(r, "text", type(r).__name__)
        if expect[mode] in said:
            break
    out.append(said)
print(json.dumps(out))
"""


def test_names_are_fixed_at_the_start_and_the_assembler_uses_them():
    """The ids of the run: the named channels of the boards read before the first packet (unnamed ones keep
    b/m/c ids, in the chunks the assembler makes); a board not read by then keeps b/m/c ids (one line); names
    that change later are one line, and the ids stay."""
    import dataclasses

    from mntes_stream.dfmux.assemble import Assembler
    from mntes_stream.dfmux.boardhk import BoardHkTracker
    from mntes_stream.dfmux.packets import SAMPLE_NS
    from mntes_stream.dfmux.publish import HkPublisher

    tr = BoardHkTracker(HkPublisher("lab", 0.1, 0.0, []))
    t0 = 1_800_000_000 * 10**9
    tr.add(_reading(t0))
    frozen = tr.freeze_names([10, 11])
    assert frozen == {(10, 0): {0: "Lab.a", 1: "Lab.b"}} and tr.status()["detector_names"] == 2
    assert tr.events == ["board 11: not read before the first sample: its detector ids are b11m<module>c<channel> "
                         "for the run"]
    asm = Assembler("lab", chunk_samples=2)
    asm.names = frozen
    chunks = []
    for k in range(2):
        chunks += asm.add(t0 + k * SAMPLE_NS, [(10, 0, 0, 1, np.arange(8, dtype=np.int32)),
                                               (11, 0, 0, 1, np.arange(8, dtype=np.int32))])
    ids = {c.board: c.detector_ids for c in chunks}
    assert ids == {10: ("Lab.a", "Lab.b", "b10m0c002", "b10m0c003"), 11: None}, ids
    renamed = _reading(t0 + 10**9)
    mr = renamed.modules[0]
    tr.add(dataclasses.replace(renamed, modules={0: dataclasses.replace(mr, names=("Lab.x",) + mr.names[1:])}))
    tr.add(dataclasses.replace(renamed, t_ns=t0 + 2 * 10**9,
                               modules={0: dataclasses.replace(mr, names=("Lab.y",) + mr.names[1:])}))
    said = [e for e in tr.events if "names differ" in e]
    assert said == ["board 10: its channel names differ from those of the start (module 0): the detector ids stay "
                    "those of the start until the bridge restarts"], tr.events
    assert tr.frozen == {(10, 0): {0: "Lab.a", 1: "Lab.b"}}


def test_a_board_answering_garbage_or_hanging_is_one_reason():
    """The poller against a real stand-in (loopback): a reply that is not JSON and a board that never answers
    are failures with their reason, and it reads again when the board answers."""
    if importlib.util.find_spec("spt3g") is None:
        pytest.skip("spt3g not installed (the g3 extra)")
    r = subprocess.run([sys.executable, "-c", _POLL, "garbage", "hang", "ok"], env=_env(), capture_output=True,
                       text=True, timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]
    first, garbage, hang, ok = json.loads(r.stdout.strip().splitlines()[-1])
    assert first == "BoardReading" and ok == "BoardReading"
    assert "not read: answered garbage (JSONDecodeError" in garbage, garbage
    assert hang.endswith("not read: tuber timed out"), hang


def test_params_keyed_by_board_names_apply(tmp_path):
    """A lab's parameter file keyed by the names its hardware map stores on the board: ``params --from-board``
    reads the board (a stand-in on loopback) and writes the converter's file keyed by detector id, each gain
    sqrt 2 x the board's amps per count (spt3g's counts_to_rms_amps through the G3 path's params_for_wiring),
    the file's phase and physics kept; the board's unnamed channels and named ones the file lacks have none;
    an unreachable board is one line."""
    if importlib.util.find_spec("spt3g") is None:
        pytest.skip("spt3g not installed (the g3 extra)")
    from mntes_stream.core.params import table1_params
    from mntes_stream.dfmux.standin import BoardState, StandInBoard, channel_name
    from mntes_stream.io.paramfile import dump_params, load_params

    board = StandInBoard(BoardState(SERIAL, named_modules=2), "127.0.0.1", 0)
    port = board.address[1]
    named = {channel_name(SERIAL, m, c): table1_params(channel_name(SERIAL, m, c), v_thev_v=2e-6 + 1e-9 * c)
             for m in (0, 1) for c in range(0, 64, 2)}
    try:
        dump_params(list(named.values()), tmp_path / "lab.toml")
        r = _cli("params", "--from-board", f"{SERIAL}=127.0.0.1:{port}", "--params", str(tmp_path / "lab.toml"),
                 "--out", str(tmp_path / "ids.toml"), "--json")
        assert r.returncode == 0, r.stderr
        out = json.loads(r.stdout)
        assert out["detectors"] == 64 and out["without_parameters"] == 512 - 64, out
    finally:
        board.close()
    got = load_params(tmp_path / "ids.toml")
    assert sorted(got) == sorted(f"b{SERIAL}m{m}c{c:03d}" for m in (0, 1) for c in range(0, 64, 2))
    # the board's gain (not the file's 1e-12 A): spt3g's ICE chain at nuller gain 2, 6.3-6.9e-11 A peak per
    # count with the channel's frequency (1.6-4.2 MHz); the file's phase (real) kept
    g = np.array([p.gain_a_per_count for p in got.values()])
    assert np.all(g.imag == 0) and np.all((g.real > 6.3e-11) & (g.real < 6.9e-11)), g
    for m in (0, 1):
        for c in range(0, 64, 2):
            assert got[f"b{SERIAL}m{m}c{c:03d}"].v_thev_v == named[channel_name(SERIAL, m, c)].v_thev_v
    r = _cli("params", "--from-board", f"{SERIAL}=127.0.0.1:{port}", "--params", str(tmp_path / "lab.toml"),
             "--out", str(tmp_path / "x.toml"))
    err = r.stderr.strip().splitlines()
    assert r.returncode == 2 and len(err) == 1, r.stderr
    assert f"board {SERIAL}: housekeeping from 127.0.0.1:{port} not read: connection refused" in err[0], err


_READ = """
import json, sys
from mntes_stream.dfmux.boardhk import read_once

r = read_once(10, "127.0.0.1", int(sys.argv[1]), 5.0)
print(json.dumps({m: mr.bias_v.tolist() for m, mr in r.modules.items()}))
"""


def test_standin_serves_the_senders_detectors_bias():
    """``standin --detectors`` (the sender's board spec and seed): the bias the bridge derives from the board's
    carrier amplitudes (spt3g's bolo_bias_voltage_rms, read over tuber on loopback) is the sender's detectors'
    bias per module (``DetectorBoard.bias_v``), on every one of the 64 channels, to rounding; a board it does not
    serve is a one-line usage error."""
    if importlib.util.find_spec("spt3g") is None:
        pytest.skip("spt3g not installed (the g3 extra)")
    from mntes_stream.dfmux.detectors import DetectorBoard

    standin = subprocess.Popen([sys.executable, "-m", "mntes_stream.dfmux.standin", "--board", "10=127.0.0.1:0",
                                "--detectors", "3:10:8:16", "--seed", "3", "--duration", "60"], env=_env(),
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        line = standin.stdout.readline()
        assert line.startswith("standin: listening 10=127.0.0.1:"), standin.stderr.read() if not line else line
        r = subprocess.run([sys.executable, "-c", _READ, line.split(":")[-1].strip()], env=_env(),
                           capture_output=True, text=True, timeout=60)
        assert r.returncode == 0, r.stderr[-2000:]
    finally:
        standin.send_signal(signal.SIGINT)
        standin.wait(timeout=30)
    got = {int(m): np.array(v) for m, v in json.loads(r.stdout).items()}
    want = DetectorBoard(10, 8, 16, seed=3).bias_v
    assert sorted(got) == list(range(8)) and all(v.shape == (64,) for v in got.values())
    assert np.ptp(want) > 0 and not np.allclose(want, DetectorBoard(10, 8, 16).bias_v)  # the seed matters
    for m in range(8):
        np.testing.assert_allclose(got[m], want[m], rtol=1e-14, atol=0)
    bad = subprocess.run([sys.executable, "-m", "mntes_stream.dfmux.standin", "--board", "10=127.0.0.1:0",
                          "--detectors", "3:11:8:16"], env=_env(), capture_output=True, text=True, timeout=60)
    assert bad.returncode == 2 and "board 11 is not served" in bad.stderr.strip().splitlines()[-1], bad.stderr


@pytest.fixture(scope="module")
def netns_mount(request):
    """A private network namespace (``netns``) and mount namespace can be made here."""
    request.getfixturevalue("netns")
    r = subprocess.run(["unshare", "-n", "-m", "true"], capture_output=True, timeout=10)
    if r.returncode:
        pytest.skip(f"unshare -n -m not permitted: {r.stderr.decode(errors='replace').strip()[:100]}")


def _params(path: Path) -> dict:
    """Parameters whose gain makes the sender's counts a detector at 0.5 R_n under 3 uV: each channel's
    counts barely move over the run (3 and 15 counts a sample), so a per-channel complex gain puts them on
    the transition. Keyed by the stand-in board's channel names."""
    from mntes_stream.core import model
    from mntes_stream.core.params import table1_params
    from mntes_stream.dfmux.packets import synthetic_counts
    from mntes_stream.dfmux.standin import channel_name
    from mntes_stream.io.paramfile import dump_params

    out = {}
    for m in range(8):
        ci, cq = synthetic_counts(SERIAL, m, np.arange(CHANNELS), np.array([0]))
        for c in range(CHANNELS):
            det = channel_name(SERIAL, m, c)  # keyed by the names the board stores (the lab's hardware map)
            p = table1_params(det, v_thev_v=3e-6)
            i_target = complex(model.tes_current_a(p, 0.5 * p.r_normal_ohm, 3e-6))
            out[det] = p.replace(gain_a_per_count=i_target / complex(ci[c, 0], cq[c, 0]))
    dump_params(list(out.values()), path)
    return out


def _post(port_host: str, body: dict) -> dict:
    import urllib.request

    req = urllib.request.Request(f"http://{port_host}/standin", data=json.dumps(body).encode(), method="POST",
                                 headers={"Content-Type": "application/json"})
    with urllib.request.urlopen(req, timeout=5) as r:
        return json.loads(r.read())


def inside(workdir: str) -> dict:
    """In the namespace: every process, the changes at set times; returns what the test checks."""
    work = Path(workdir)
    subprocess.run(["ip", "link", "set", "lo", "up"], check=True)
    (work / "hosts").write_text(f"127.0.0.1 localhost\n127.0.0.1 iceboard{SERIAL:04d}.local\n")
    subprocess.run(["mount", "--bind", str(work / "hosts"), "/etc/hosts"], check=True)
    py = [sys.executable, "-m"]
    z = ["-m", "client", "-e", "tcp/127.0.0.1:7447"]
    _params(work / "params.toml")
    (work / "converter.toml").write_text('[converter]\nparams = "params.toml"\nkind = "exact"\n')
    logs = {name: open(work / f"{name}.log", "w") for name in ("standin", "router", "converter", "record", "bridge",
                                                              "monitor")}
    procs = {}

    def start(name, argv, stdout=None):
        procs[name] = subprocess.Popen(argv, cwd=work, stdout=stdout or logs[name], stderr=logs[name])

    def wait_for(name, text, timeout_s=60.0):
        t_end = time.monotonic() + timeout_s
        while time.monotonic() < t_end:
            if text in (work / f"{name}.log").read_text():
                return
            if procs[name].poll() is not None:
                raise SystemExit(f"{name} exited: {(work / f'{name}.log').read_text()[-1500:]}")
            time.sleep(0.1)
        raise SystemExit(f"{name}: no {text!r} in {timeout_s} s: {(work / f'{name}.log').read_text()[-1500:]}")

    out: dict = {}
    try:
        start("standin", py + ["mntes_stream.dfmux.standin", "--board", str(SERIAL)])
        start("router", py + ["mntes_stream", "router", "-l", "tcp/127.0.0.1:7447"])
        wait_for("standin", "standin: listening")
        start("converter", py + ["mntes_stream", "serve", "--config", "converter.toml"] + z)
        start("record", py + ["mntes_stream", "record", "--dir", "rec"] + z)
        wait_for("converter", "subscribed to")
        wait_for("record", "recording mntes/lab")
        start("monitor", py + ["mntes_stream", "monitor", "--text"] + z)
        start("bridge", py + ["mntes_stream", "dfmux-bridge", "--interface", "127.0.0.1", "--board", str(SERIAL),
                              "--t-bath-k", "0.1", "--bias", f"{SERIAL}/7=4e-6", "--bias", f"{SERIAL}/*=3e-6",
                              "--hk-every", str(HK_EVERY_S), "--hk-stale", str(HK_STALE_S), "--hk-timeout", "0.5",
                              "--params", "params.toml", "--json"] + z,
              stdout=open(work / "bridge.json", "w"))
        # checkable counts: the parameters (_params) and the power check below are made from synthetic_counts
        sender = subprocess.Popen(py + ["mntes_stream.dfmux.sender", "--board", f"3:{SERIAL}:8:{CHANNELS}",
                                        "--counts", "checkable", "--wait-listener", "60", "--duration",
                                        str(DURATION_S)],
                                  cwd=work, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        board = "127.0.0.1:80"
        from mntes_stream.dfmux.sender import wait_listener

        wait_listener(60)  # the bridge listens: the sender starts sending
        t_end = time.monotonic() + 30
        while _post(board, {})["dumps"] < 2 and time.monotonic() < t_end:  # the bridge has read the board
            time.sleep(0.1)
        time.sleep(0.8)
        out["retune"] = _post(board, {"retune": {"module": 3, "factor": 0.9}})
        out["latch"] = _post(board, {"state": {"module": 1, "channel": 5, "state": "latched"}})
        out["rail"] = _post(board, {"rail": {"module": 2, "what": "carrier"}})
        time.sleep(1.5)
        out["hang"] = _post(board, {"mode": "hang"})
        snd_out, snd_err = sender.communicate(timeout=60)
        if sender.returncode:
            raise SystemExit(f"sender failed: {snd_err[-500:]}")
        out["sender"] = json.loads(snd_out.strip().splitlines()[-1])
        ps = subprocess.run(py + ["mntes_stream", "ps", "--json", "--timeout", "3"] + z, cwd=work,
                            capture_output=True, text=True, timeout=60)
        out["ps"] = json.loads(ps.stdout) if ps.returncode == 0 else ps.stderr
        time.sleep(0.5)
        procs["bridge"].send_signal(signal.SIGTERM)
        procs["bridge"].wait(timeout=30)
        time.sleep(1.5)  # the converter's last power reaches the recorder
        for name in ("converter", "record", "monitor"):
            procs[name].send_signal(signal.SIGTERM)
            procs[name].wait(timeout=30)
    finally:
        for p in procs.values():
            if p.poll() is None:
                p.kill()
                p.wait()
        for f in logs.values():
            f.close()
    out["logs"] = {name: (work / f"{name}.log").read_text() for name in logs}
    out["bridge_result"] = json.loads((work / "bridge.json").read_text() or "null")
    return out


def _recorded(rec: Path):
    from mntes_stream.io.mcap import iter_messages
    from mntes_stream.io.messages import decode

    bias, flags, power = {}, {}, {}
    for r in iter_messages(rec):
        if r.schema_name not in ("mntes.hk", "mntes.power"):
            continue
        m = decode(r.payload)
        if r.schema_name == "mntes.power":
            power.setdefault(m.module, []).append(m)
        elif m.sensor == "bias":
            bias.setdefault(m.module, []).append(m)
        elif m.sensor == "readout_flags":
            flags.setdefault(m.module, []).append(m)
    return bias, flags, power


def test_board_housekeeping_end_to_end(netns_mount, tmp_path):
    """Retune module 3 (carrier x 0.9) mid-run: its recorded bias steps by 0.9, the other modules' stay; the
    converter's power of module 3 is the model's inverse at the recorded bias of each sample (the new one after
    the step); a latched channel and a railed carrier flag their samples UNTUNED and RAILED; the board that
    stops answering is one line, counted, and its samples flagged HK_STALE after the limit."""
    from mntes_stream.core import flags as fl
    from mntes_stream.core import model

    proc = subprocess.run(["unshare", "-n", "-m", sys.executable, __file__, str(tmp_path)], env=_env(),
                          capture_output=True, text=True, timeout=150)
    assert proc.returncode == 0, proc.stderr[-3000:]
    r = json.loads(proc.stdout.strip().splitlines()[-1])
    logs = r["logs"]
    where = "\n".join(f"== {k}\n{v[-1500:]}" for k, v in logs.items())
    assert "Traceback" not in where, where
    bridge_log = logs["bridge"]
    result = r["bridge_result"]
    assert result and result["lost"] == 0 and result["gap_samples"] == 0, where
    # the board that stopped answering: one line naming it, counted; then stale
    assert bridge_log.count(f"board {SERIAL}: housekeeping from iceboard{SERIAL:04d}.local:80 not read: "
                            "tuber timed out") == 1, where
    assert f"board {SERIAL}: no good housekeeping for {HK_STALE_S:g} s" in bridge_log, where
    assert result["board_hk_failures"] >= 1 and result["board_hk"][str(SERIAL)]["stale"] is True, result
    assert result["board_hk"][str(SERIAL)]["named_channels"] == 512, result["board_hk"]
    # the configured 4e-6 V of module 7 disagrees with the board's ~3e-6 V: one warning line
    assert bridge_log.count(f"board {SERIAL} module 7: configured bias 4e-06 V differs from the board's") == 1, where

    bias, flags, power = _recorded(tmp_path / "rec")
    t_retune = r["retune"]["t_ns"]
    # the board is read before the bridge receives its first packet (its names): only the board's bias (its 64
    # channels) is published, never the configured table's
    steps = {}
    for m, msgs in bias.items():
        board = msgs
        assert all(h.channels.size == 64 for h in msgs), m
        t = np.concatenate([h.t_ns for h in board])
        v = np.concatenate([h.value for h in board])
        steps[m] = (t, v, np.flatnonzero(np.any(v[1:] != v[:-1], axis=1)))
    # module 3: one step by 0.9, stamped by the board within a poll or two of the retune
    t3, v3, ch3 = steps[3]
    assert ch3.size == 1, (t3, v3[:, 0])
    k = int(ch3[0])
    np.testing.assert_allclose(v3[k + 1] / v3[k], 0.9, rtol=1e-9)
    assert t_retune <= t3[k + 1] <= t_retune + int((2 * HK_EVERY_S + 1.0) * 1e9), (t3[k + 1] - t_retune) / 1e9
    assert t3[k + 1] - t3[k] == 1  # the step: old value 1 ns before, new at the board's stamp
    assert np.all(np.abs(v3[0] / 3e-6 - 1) < 0.03)  # the board's ~2.95e-6 V, not the table's
    for m in (0, 1, 2, 4, 5, 6, 7):  # untouched: one value from the board's first reading on
        assert steps[m][2].size == 0, (m, steps[m][1][:, 0])
    np.testing.assert_allclose(steps[7][1][0], v3[0], rtol=0.01)  # not the configured 4e-6 V

    # the converter's power of module 3 at each sample is the model's inverse at the recorded bias there
    from mntes_stream.dfmux.packets import SAMPLE_NS, synthetic_counts
    from mntes_stream.io.paramfile import load_params

    params = load_params(tmp_path / "params.toml")
    # the board's names are the detector ids of every power chunk, from the first; the parameters keyed by them
    # apply: module 3's power is exactly the model's (below, each row's parameters looked up by its name)
    from mntes_stream.dfmux.standin import channel_name

    assert sorted(power) == list(range(8))
    for m, chunks in power.items():
        for pc in chunks:
            assert pc.detector_ids == tuple(channel_name(SERIAL, m, c) for c in pc.channels.tolist()), pc.detector_ids
    import h5py

    from mntes_stream.dfmux.bridge import ledger_line

    # and the export of the recording lists them (HDF5, as the lab recipe exports)
    ex = _cli("export", str(tmp_path / "rec"), "--out", str(tmp_path / "lab.h5"), "-q")
    assert ex.returncode == 0, ex.stderr[-2000:]
    with h5py.File(tmp_path / "lab.h5", "r") as f:
        exported = sorted(d.decode() if isinstance(d, bytes) else str(d) for g in f if "detectors" in f[g]
                          for d in f[g]["detectors"][()])
    assert exported == sorted(channel_name(SERIAL, m, c) for m in range(8) for c in range(CHANNELS)), exported[:5]
    # the monitor names them too (its list of detectors not in the transition)
    assert f"not in transition: {channel_name(SERIAL, 0, 0)}" in logs["monitor"], logs["monitor"][-1500:]
    assert result["detector_names"] == 512 and "512 channels named by the boards" in ledger_line(result), where
    t_step = int(t3[k + 1])
    n_after = n_checked = 0
    for pc in power[3]:
        ts = pc.times_ns()
        use = ts > t3[0] + 10**9  # the board's bias in force (the table's before its first reading)
        if not use.any():
            continue
        kk = (ts - r["sender"]["t0_ns"]) // SAMPLE_NS
        ci, cq = synthetic_counts(SERIAL, 3, pc.channels, kk)
        for row, det in enumerate(pc.detector_ids):
            p = params[det]
            i_meas = p.gain_a_per_count * (ci[row] + 1j * cq[row])
            v = np.interp(ts - t3[0], t3 - t3[0], v3[:, pc.channels[row]])
            want = model.invert_current(p, i_meas, 0.1, 0.0, v).p_opt_w
            sel = use & np.isfinite(pc.p_opt_w[row])
            np.testing.assert_allclose(pc.p_opt_w[row][sel], want[sel], rtol=1e-6, atol=1e-21)
            n_checked += int(sel.sum())
            after = sel & (ts > t_step)
            n_after += int(after.sum())
            if after.any():  # and not what the old bias would give
                old = model.invert_current(p, i_meas, 0.1, 0.0, v3[k, pc.channels[row]]).p_opt_w
                assert np.all(np.abs(old[after] - pc.p_opt_w[row][after]) > 1e-15), det
    assert n_after > 500 and n_checked > 1000, (n_after, n_checked)

    # tuning state and rails: flags from the board's reading on, not before
    def flag_frac(m, rows, bit, t_lo, t_hi):
        hit = tot = 0
        for pc in power[m]:
            ts = pc.times_ns()
            sel = (ts >= t_lo) & (ts < t_hi)
            f = pc.flags[rows][:, sel]
            hit += int(np.count_nonzero(f & bit))
            tot += f.size
        return hit / max(tot, 1), tot

    lat = [h for h in flags[1] if np.any(h.value[0] != 0) and not np.any(h.value[0].astype(int) & fl.HK_STALE)]
    assert lat, [h.value for h in flags[1]]
    t_lat = int(lat[0].t_ns[0])
    assert t_retune <= t_lat, (t_lat - t_retune) / 1e9
    frac, n = flag_frac(1, [5], fl.UNTUNED, t_lat, t_lat + 2 * 10**9)
    assert frac == 1.0 and n > 100, (frac, n)
    assert flag_frac(1, [5], fl.UNTUNED, 0, t_retune)[0] == 0.0
    assert flag_frac(1, [4, 6], fl.UNTUNED, 0, 2**62)[0] == 0.0
    rail = [h for h in flags[2] if np.all(h.value[0].astype(int) & fl.RAILED)]
    assert rail, [h.value for h in flags[2]]
    assert flag_frac(2, list(range(CHANNELS)), fl.RAILED, int(rail[0].t_ns[0]), 2**62)[0] == 1.0
    # stale: every module from the stale time on, none before the board stopped answering
    stale_t = {m: [int(h.t_ns[0]) for h in flags[m] if np.all(h.value[0].astype(int) & fl.HK_STALE)] for m in range(8)}
    assert all(len(v) == 1 for v in stale_t.values()), stale_t
    t_stale = stale_t[0][0]
    assert r["hang"]["t_ns"] < t_stale <= r["hang"]["t_ns"] + int((HK_STALE_S + HK_EVERY_S + 2.0) * 1e9)
    for m in range(8):
        frac, n = flag_frac(m, list(range(CHANNELS)), fl.HK_STALE, t_stale, 2**62)
        assert frac == 1.0 and n > 0, (m, frac, n)
        assert flag_frac(m, list(range(CHANNELS)), fl.HK_STALE, 0, r["hang"]["t_ns"])[0] == 0.0
    # the bridge's status: the disagreeing bias, the changes
    # (module 3 disagrees with the table too once retuned: 0.9 x 2.95e-6 V against 3e-6 V)
    assert set(result["bias_disagree"]) == {f"{SERIAL}/3", f"{SERIAL}/7"}, result["bias_disagree"]
    assert result["bias_disagree"][f"{SERIAL}/7"]["configured_v"] == 4e-6
    assert any("module 3: bias changed (median ratio 0.9)" in c for c in result["hk_changes"]), result["hk_changes"]
    assert result["readout_flagged"][f"{SERIAL}/2"] == ["hk_stale", "railed"], result["readout_flagged"]
    # tuning against the parameters: the stand-in's R_normal 2 Ohm, the parameters' 1 Ohm (Table 1), every
    # detector with parameters named in the status, one line per module
    assert result["tuning_disagree_total"] == 8 * CHANNELS, result["tuning_disagree_total"]
    assert result["tuning_disagree"][f"b{SERIAL}m3c000"]["r_normal_ohm"] == {"board": 2.0, "params": 1.0}
    assert bridge_log.count("detector(s) tuned unlike their parameters") == 8, where
    # ps sees it live: the bridge's warnings and status fields
    (live,) = [b for b in r["ps"]["services"] if b["service"] == "dfmux-bridge"]
    assert live["board_hk"][str(SERIAL)]["stale"] is True and live["tuning_disagree_total"] == 8 * CHANNELS, live
    assert any("no good housekeeping" in w for w in live["warnings"]), live["warnings"]


if __name__ == "__main__":
    print(json.dumps(inside(sys.argv[1]), default=str))

"""Bath temperature from OCS HK G3 files (issue 25 item 2, offline): ``convert --hk DIR --t-bath-field NAME``.

The HK files are written by ocs's own aggregator (so3g's HKSessionHelper inside) in a child process with
so3g; the G3 run by spt3g 1.0.2 in a child without so3g (it has DfMux housekeeping and no thermometer);
every command runs as its own process, so the G3 and HK files are read on spt3g 1.0.2.
"""

from __future__ import annotations

import importlib.util
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("spt3g.core", reason="the g3 extra (spt3g) is not installed")
if importlib.util.find_spec("ocs") is None or importlib.util.find_spec("so3g") is None:
    pytest.skip("the ocs extra (ocs, so3g: the HK writer) is not installed", allow_module_level=True)

from test_g3_envs import ALONE, TESTS, cli  # noqa: E402

FIELD = "observatory.LS372.feeds.temperatures.Channel_06_T"
T0_S = 1_700_000_000.0  # test_g3's run starts here and lasts 0.39 s
# ocs's aggregator, driven as its agent drives it: (data, feed) pairs in its queue, run(), close().
HK_WRITER = r"""
import json, queue, sys
import numpy as np
from ocs.agents.aggregator.drivers import Aggregator
out, feeds = sys.argv[1], json.loads(sys.argv[2])
q = queue.Queue()
agg = Aggregator(q, time_per_file=3600, data_dir=out)
for f in feeds:
    data = {f["block"]: {"block_name": f["block"], "timestamps": [float(t) for t in f["t"]],
                         "data": {k: [float(x) for x in v] for k, v in f["fields"].items()}}}
    q.put((data, {"address": f["address"], "session_id": 1, "agg_params": {"frame_length": 60}}))
    agg.run()
agg.close()
"""
RUN_WRITER = ALONE + """
sys.path.insert(0, sys.argv[1])
import test_g3 as t
from pathlib import Path
from mntes_stream.core.params import table1_params
from mntes_stream.io.paramfile import dump_params
d = Path(sys.argv[2])
t.write(t.raw_frames(bath=False), d / "raw.g3")
dump_params([table1_params(n) for n in t.LAYOUT], d / "names.toml")
"""


def write_hk(d: Path, t_bath_k: float, slope_k_per_s: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """HK files of a fake LS372 at 10 Hz around the run (two blocks, two feeds); the times and values written."""
    t = T0_S - 2 + np.arange(41) * 0.1
    v = t_bath_k + slope_k_per_s * (t - T0_S)
    feeds = [{"address": "observatory.LS372.feeds.temperatures", "block": "temps", "t": t[:20].tolist(),
              "fields": {"Channel_06_T": v[:20].tolist(), "Channel_01_T": [4.0] * 20}},
             {"address": "observatory.LS240.feeds.temperatures", "block": "b", "t": t.tolist(),
              "fields": {"Channel_1_T": [40.0] * t.size}},
             {"address": "observatory.LS372.feeds.temperatures", "block": "temps", "t": t[20:].tolist(),
              "fields": {"Channel_06_T": v[20:].tolist(), "Channel_01_T": [4.0] * 21}}]
    p = subprocess.run([sys.executable, "-c", HK_WRITER, str(d), json.dumps(feeds)], capture_output=True, text=True,
                       timeout=60)
    assert p.returncode == 0, p.stderr[-2000:]
    return t, v


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    d = tmp_path_factory.mktemp("ocs_run")
    p = subprocess.run([sys.executable, "-c", RUN_WRITER, str(TESTS), str(d)], capture_output=True, text=True,
                       timeout=120)
    assert p.returncode == 0, p.stderr[-2000:]
    return d


def messages(path, kind):
    from mntes_stream.io.mcap import Session
    from mntes_stream.io.messages import decode

    return [(m.topic, decode(m.payload)) for m in Session(path).iter_messages() if f"/{kind}" in m.topic]


def convert(run, out, *extra):
    p = cli(["convert", run / "raw.g3", out, "--params", run / "names.toml", "-q", "--json", *extra])
    assert p.returncode == 0, p.stderr[-2000:]
    return json.loads(p.stdout)


SO3G_READER = r"""
import glob, json, sys
from so3g.hk import HKArchiveScanner
scanner = HKArchiveScanner()
for f in sorted(glob.glob(sys.argv[1] + "/**/*.g3", recursive=True)):
    scanner.process_file(f)
arc = scanner.finalize()
(t, y), = arc.simple([sys.argv[2]])
print(json.dumps({"fields": sorted(arc.get_fields()[0]), "t": list(map(float, t)), "v": list(map(float, y))}))
"""


def test_read_fields_gives_what_ocs_aggregator_wrote_as_so3g_reads_it(tmp_path):
    t, v = write_hk(tmp_path / "hk", 0.1, 0.01)
    code = ALONE + f"""
import json
from mntes_stream.g3.ocs_hkfile import read_fields
s = read_fields(sys.argv[1], [{FIELD!r}, "observatory.LS240.feeds.temperatures.Channel_1_T"])
print(json.dumps({{k: [x.t_ns.tolist(), x.value.tolist()] for k, x in s.items()}}))
"""
    p = subprocess.run([sys.executable, "-c", code, str(tmp_path / "hk")], capture_output=True, text=True, timeout=60)
    assert p.returncode == 0, p.stderr[-2000:]
    ours = json.loads(p.stdout)
    ticks = np.array([round(x * 1e8) for x in t]) * 10  # G3Time(t * G3Units.s): 10 ns ticks
    np.testing.assert_array_equal(np.array(ours[FIELD][0], dtype=np.int64), ticks)
    np.testing.assert_array_equal(ours[FIELD][1], v)
    assert ours["observatory.LS240.feeds.temperatures.Channel_1_T"][1] == [40.0] * 41
    # so3g's own reader (HKArchiveScanner, in a process with so3g) names and reads the same
    p = subprocess.run([sys.executable, "-c", SO3G_READER, str(tmp_path / "hk"), FIELD], capture_output=True,
                       text=True, timeout=60)
    assert p.returncode == 0, p.stderr[-2000:]
    theirs = json.loads(p.stdout)
    assert FIELD in theirs["fields"] and theirs["v"] == ours[FIELD][1]
    np.testing.assert_allclose(np.array(theirs["t"]) * 1e9, ours[FIELD][0], rtol=0, atol=1e3)


@pytest.fixture(scope="module")
def converted(run, tmp_path_factory):
    """``convert RUN.g3 OUT.mcap --hk DIR --t-bath-field ...`` of OCS readings at a constant 0.1 K."""
    d = tmp_path_factory.mktemp("ocs_converted")
    write_hk(d / "hk", 0.1)
    res = convert(run, d / "ocs.mcap", "--hk", d / "hk", "--t-bath-field", FIELD)
    return d, res


def test_convert_takes_the_bath_from_ocs_hk_files(run, converted, tmp_path):
    d, got = converted
    ref = convert(run, tmp_path / "ref.mcap", "--t-bath-default-k", "0.1")
    assert got["ledger_line"] == ref["ledger_line"] == "received 8 chunks: converted 8; lost 0 of 8"
    hk = messages(d / "ocs.mcap", "hk/t_bath")
    # every reading of the field (not the other fields, feeds, blocks), as written, in K, in time order
    assert [float(m.value[0]) for _, m in hk] == [0.1] * 41
    assert np.all(np.diff([int(m.t_ns[0]) for _, m in hk]) == 100_000_000)
    # 0.1 K from OCS converts as 0.1 K given (no bath, or another, would not: NaN and HK_MISSING, or other power)
    a, b = messages(tmp_path / "ref.mcap", "power"), messages(d / "ocs.mcap", "power")
    assert len(a) == len(b) == 8 and sum(np.isfinite(m.p_opt_w).sum() for _, m in b) > 50
    for (ta, ma), (tb, mb) in zip(a, b):
        assert ta == tb
        np.testing.assert_array_equal(ma.p_opt_w, mb.p_opt_w)
        np.testing.assert_array_equal(ma.flags, mb.flags)


def without_bath(d: Path, out: Path) -> Path:
    """The inputs of the conversion in ``d`` (counts, bias), without the bath: a recording without a thermometer."""
    from mntes_stream.io.mcap import McapFileWriter, Session

    with McapFileWriter(out) as w:
        for m in Session(d / "ocs.mcap").iter_messages():
            if "/t_bath" not in m.topic and "/power/" not in m.topic and "/status/" not in m.topic:
                w.write(m.topic, m.payload, m.log_time_ns)
    return out


def test_a_recording_without_a_thermometer_takes_ocs_hk_too(converted, tmp_path):
    d, _ = converted
    without_bath(d, tmp_path / "rec.mcap")
    p = cli(["convert", tmp_path / "rec.mcap", tmp_path / "again.mcap", "-q", "--json", "--hk", d / "hk",
             "--t-bath-field", FIELD])
    assert p.returncode == 0, p.stderr[-2000:]
    assert json.loads(p.stdout)["ledger_line"] == "received 8 chunks: converted 8; lost 0 of 8"
    for (ta, ma), (tb, mb) in zip(messages(d / "ocs.mcap", "power"), messages(tmp_path / "again.mcap", "power"),
                                  strict=True):
        assert ta == tb
        np.testing.assert_array_equal(ma.p_opt_w, mb.p_opt_w)
    # a recording with its own thermometer is refused in one line: two would mix
    p = cli(["convert", d / "ocs.mcap", tmp_path / "x.mcap", "-q", "--hk", d / "hk",
             "--t-bath-field", FIELD])
    assert p.returncode == 2 and p.stderr.count("\n") == 1 and "has its own t_bath" in p.stderr, p.stderr


def test_a_field_not_in_the_files_is_one_line_with_the_closest_names(run, converted, tmp_path):
    d, _ = converted
    p = cli(["convert", run / "raw.g3", tmp_path / "o.mcap", "--params", run / "names.toml", "-q",
             "--hk", d / "hk", "--t-bath-field", FIELD.replace("06", "07")])
    assert p.returncode == 2 and p.stderr.count("\n") == 1, p.stderr
    assert "no field" in p.stderr and FIELD in p.stderr  # the closest names
    p = cli(["convert", run / "raw.g3", tmp_path / "o.mcap", "--params", run / "names.toml", "-q",
             "--hk", run / "raw.g3", "--t-bath-field", FIELD])  # not an HK file
    assert p.returncode == 2 and "not an OCS HK file" in p.stderr and p.stderr.count("\n") == 1, p.stderr


def test_replay_publishes_the_ocs_readings_with_the_recording(converted, tmp_path):
    from mntes_stream.io.transport import QueueSubscriber, free_tcp_port, loopback, open_session

    d, _ = converted
    rec = without_bath(d, tmp_path / "rec.mcap")
    port = free_tcp_port()
    got = []
    with open_session(loopback(port)) as z:
        sub = QueueSubscriber(z, ["mntes/lab/**"])
        p = cli(["replay", rec, "--afap", "--wait-s", "10", "--json", "-q", "--hk", d / "hk", "--t-bath-field", FIELD,
                 "-e", f"tcp/127.0.0.1:{port}"])
        assert p.returncode == 0, p.stderr[-2000:]
        for _ in range(200):
            item = sub.get(timeout_s=0.1)
            if item is None and got:
                break
            if item is not None:
                got.append(item[0])
        sub.close()
    from mntes_stream.io.mcap import Session

    session = Session(rec)
    t = np.array([round(x * 1e8) * 10 for x in T0_S - 2 + np.arange(41) * 0.1])  # as written (10 ns ticks)
    inside = int(((t >= session.start_ns) & (t <= session.end_ns)).sum())
    # the readings within the recording's span and one on each side of it; the counts as recorded
    sides = int((t < session.start_ns).any()) + int((t > session.end_ns).any())
    assert sum(k.endswith("/hk/t_bath") for k in got) == inside + sides and inside > 4, got
    assert sum("/counts/" in k for k in got) == 8


def test_g3_bridge_publishes_the_ocs_bath_with_the_run(run, converted):
    from mntes_stream.io.messages import decode
    from mntes_stream.io.transport import QueueSubscriber, free_tcp_port, loopback, open_session

    d, _ = converted
    port = free_tcp_port()
    got = []
    with open_session(loopback(port)) as z:
        sub = QueueSubscriber(z, ["mntes/lab/**"])
        p = cli(["g3-bridge", "--from", run / "raw.g3", "--json", "--hk", d / "hk", "--t-bath-field", FIELD,
                 "-e", f"tcp/127.0.0.1:{port}"])  # the run has no thermometer: without --hk it could not start
        assert p.returncode == 0, p.stderr[-2000:]
        for _ in range(200):
            item = sub.get(timeout_s=0.1)
            if item is None and got:
                break
            if item is not None:
                got.append((item[0], decode(item[1])))
        sub.close()
    bath = [m for k, m in got if k.endswith("/hk/t_bath")]
    counts_end = max(int(m.times_ns()[-1]) for k, m in got if "/counts/" in k)
    t = np.concatenate([m.t_ns for m in bath])
    # every reading up to the run's last sample and the first one after it, in order, as written
    assert np.all(np.diff(t) > 0) and t[-1] > counts_end and t[-2] <= counts_end and t[0] < T0_S * 1e9
    assert [float(m.value[0]) for m in bath] == [0.1] * len(bath)
    res = json.loads(p.stdout)
    assert res["lost"] == 0 and res["spt3g"].startswith("spt3g 1.0.2 (")

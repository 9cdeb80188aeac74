"""Recording sessions stay apart: two runs into one folder are never read as one observation."""

from __future__ import annotations

import subprocess
import sys
import warnings

import h5py
import numpy as np
import pytest

from mntes_stream.errors import TransportError
from mntes_stream.io import mcap as mio
from mntes_stream.io.mcap.recovery import file_session
from mntes_stream.io.messages import HousekeepingChunk

T0_NS = 1_700_000_000_000_000_000


def _record(directory, t0_ns: int, n: int, close: bool = True) -> mio.RotatingMcapWriter:
    w = mio.RotatingMcapWriter(directory, "mntes", flush_interval_s=0.05, rotate_bytes=0, rotate_s=0)
    for k in range(n):
        t = t0_ns + k * 100_000_000
        msg = HousekeepingChunk(setup="lab", sensor="t_bath", seq=k, t_ns=np.array([t]), value=np.array([0.1]), unit="K")
        w.write("mntes/lab/hk/t_bath", msg.to_bytes(), t)
    w.flush()
    if close:
        w.close()
    return w


def test_two_runs_into_one_folder_are_two_sessions_and_the_newest_is_read(tmp_path):
    first = _record(tmp_path, T0_NS, 5)
    second = _record(tmp_path, T0_NS + 3_600_000_000_000, 3)  # an hour later, same folder
    assert first.session_id != second.session_id
    assert [file_session(p) for p in sorted(tmp_path.glob("*.mcap"))] == [first.session_id, second.session_id]
    with pytest.warns(mio.SessionsWarning, match=r"2 recording sessions in .*: .* \(1 file\(s\)\), .*reading the newest"):
        s = mio.Session(tmp_path)
    assert s.session == second.session_id and s.count() == 3 and s.start_ns == T0_NS + 3_600_000_000_000
    assert [sid for sid, _ in s.sessions] == [first.session_id, second.session_id]
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a named session, or all of them, is read without a warning
        assert mio.Session(tmp_path, session=first.session_id).count() == 5
        assert mio.Session(tmp_path, session="all").count() == 8
    with pytest.raises(TransportError, match="no recording session 'nope'"):
        mio.Session(tmp_path, session="nope")


def test_a_recorder_restarted_after_a_crash_continues_its_session(tmp_path):
    killed = _record(tmp_path, T0_NS, 4, close=False)  # no footer: its writer died
    again = _record(tmp_path, T0_NS + 1_000_000_000, 4)
    assert again.session_id == killed.session_id
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", mio.TruncatedFileWarning)
        warnings.simplefilter("error", mio.SessionsWarning)
        assert mio.Session(tmp_path).count() == 8
    third = _record(tmp_path, T0_NS + 9_000_000_000, 2)  # after a clean stop: a new session
    assert third.session_id != again.session_id


def test_two_up_runs_into_one_folder_inspect_and_export_keep_them_apart(tmp_path):
    out = tmp_path / "up"
    cmd = [sys.executable, "-m", "mntes_stream", "up", "--duration", "2", "--modules", "1", "--channels", "8",
           "--minimal", "--out", str(out), "-q"]
    for _ in range(2):
        done = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
        assert done.returncode == 0, done.stderr[-2000:]
    files = sorted((out / "recordings").glob("*.mcap"))
    assert len(files) == 2 and file_session(files[0]) != file_session(files[1])
    shown = subprocess.run([sys.executable, "-m", "mntes_stream", "inspect", str(out)], capture_output=True,
                           text=True, timeout=120)
    assert shown.returncode == 0, shown.stderr
    assert shown.stdout.startswith(f"2 recording sessions here; this is the newest, {file_session(files[1])}")
    assert f"  session {file_session(files[0])}: 1 file(s), {files[0]}" in shown.stdout
    exported = subprocess.run([sys.executable, "-m", "mntes_stream", "export", str(out), "--out", str(tmp_path / "p.h5")],
                              capture_output=True, text=True, timeout=300)
    assert exported.returncode == 0, exported.stderr
    said = [line for line in exported.stderr.splitlines() if "recording sessions" in line]
    assert len(said) == 1 and said[0].startswith("mntes-stream: warning: 2 recording sessions in "), exported.stderr
    with h5py.File(tmp_path / "p.h5") as f:
        t = np.concatenate([g["time_ns"][:] for g in f.values() if isinstance(g, h5py.Group) and "time_ns" in g])
    newest = mio.Session(files[1])
    # Only the newest run: no sample before its start, and no hole of the time between the runs.
    assert t.min() >= newest.start_ns - 1_000_000_000 and (t.max() - t.min()) / 1e9 < 10, (t.min(), t.max())


def test_inspect_says_a_file_being_written_is_being_written_not_damaged(tmp_path):
    """A live recording (its writer holds the file open) is not a dead one: inspect says so and exits 0; once its
    writer is gone without finishing it (killed), the same bytes are UNFINISHED."""
    w = _record(tmp_path, T0_NS, 30, close=False)  # written and flushed, still open
    cmd = [sys.executable, "-m", "mntes_stream", "inspect", str(tmp_path)]
    live = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert live.returncode == 0, live.stderr
    assert f"{w.current_path}: 30 messages" in live.stdout and "being written (its recorder runs)" in live.stdout
    assert "UNFINISHED" not in live.stdout and "DAMAGED" not in live.stdout + live.stderr
    w._current._file.close()  # the writer dies: its lock goes with its file handle, the footer never comes
    dead = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert "UNFINISHED (" in dead.stdout and "being written" not in dead.stdout, dead.stdout

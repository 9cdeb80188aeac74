"""Recovery that tells the truth (issue 22 item 3): a killed recording with a damaged chunk, a full disk.

The recording is written by the recorder's own writer (RotatingMcapWriter, one
chunk per flush) in a process that is then SIGKILLed; damage is a flipped
byte inside one chunk's compressed body. What was lost is known independently:
every batch of the source has its own receive time, so the messages of a chunk
are the intact file's messages at that chunk's time.
"""

from __future__ import annotations

import contextlib
import json
import os
import subprocess
import sys
import warnings
from pathlib import Path

import pytest
from mcap.reader import make_reader

from mntes_stream.cli import main
from mntes_stream.io import mcap as mio
from mntes_stream.io.mcap.recovery import index_file

T0 = 1_700_000_000_000_000_000

@pytest.fixture(scope="module")
def killed(tmp_path_factory):
    """``(bytes of the SIGKILLed recording, its chunk refs in file order, messages written)``."""
    from mcap_helpers import writer_recording

    path, written = writer_recording(tmp_path_factory.mktemp("killed"), 3.0, finish=False)
    chunks = sorted(index_file(path).chunks, key=lambda c: c.offset)
    assert not index_file(path).complete and len(chunks) > 20
    return path.read_bytes(), chunks, written


def _messages(path):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", mio.TruncatedFileWarning)
        return list(mio.iter_messages(path))


def _damaged(tmp_path, killed, k, name="bad.mcap") -> tuple[Path, object, list]:
    """The killed recording with chunk ``k``'s compressed body hit; returns it, the chunk, its messages."""
    data, chunks, _ = killed
    intact = tmp_path / "intact.mcap"
    intact.write_bytes(data)
    c = chunks[k]
    bad = bytearray(data)
    bad[c.offset + c.length - 20] ^= 0xFF
    path = tmp_path / name
    path.write_bytes(bytes(bad))
    held = [m for m in _messages(intact) if c.start_ns <= m.log_time_ns <= c.end_ns]
    return path, c, held


def _cli(capsys, *argv) -> tuple[int, str, str]:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", mio.TruncatedFileWarning)
        rc = main([str(a) for a in argv])
    out = capsys.readouterr()
    return rc, out.out, out.err


def test_verify_and_recover_of_a_killed_recording_with_a_damaged_chunk(killed, tmp_path, capsys):
    data, _, written = killed
    path, c, held = _damaged(tmp_path, killed, 10)
    assert len(_messages(tmp_path / "intact.mcap")) == written and 0 < len(held) < written
    topics = {}
    for m in held:
        topics[m.topic] = topics.get(m.topic, 0) + 1

    rc, out, err = _cli(capsys, "inspect", "--verify", tmp_path / "intact.mcap")
    assert rc == 0 and "every chunk verified" in out and "DAMAGED" not in out + err

    rc, out, err = _cli(capsys, "inspect", "--verify", path)
    assert rc == 2 and "every chunk verified" not in out and "DAMAGED" in err
    line = next(x for x in out.splitlines() if "damaged chunk at byte" in x)
    assert f"byte {c.offset}: {len(held)} messages" in line
    assert all(f"{t} x{n}" in line for t, n in topics.items())
    assert f"LOST {len(held)} messages" in out and f"{written - len(held)} messages readable" in out
    rc, out, _ = _cli(capsys, "inspect", "--verify", "--json", path)
    doc = json.loads(out)
    assert rc == 2 and doc["complete"] is False and doc["verified"][0]["lost_messages"] == len(held)
    assert doc["verified"][0]["damage"][0]["start_ns"] == c.start_ns

    fixed = tmp_path / "fixed.mcap"
    rc, out, err = _cli(capsys, "recover", path, fixed)
    assert rc == 0 and "0 unreadable" not in out and f"LOST {len(held)} messages" in out
    assert f"damaged chunk at byte {c.offset}: {len(held)} messages" in err
    assert not (tmp_path / "fixed.mcap.partial").exists()
    with open(fixed, "rb") as f:  # the reference reader: a finished file holding every readable message
        reader = make_reader(f)
        assert reader.get_summary().statistics.message_count == written - len(held)
        meta = {m.name: m.metadata for m in reader.iter_metadata()}
    assert meta["mntes.damaged"]["messages_lost"] == str(len(held))
    assert json.loads(meta["mntes.damaged"]["spans_ns"]) == [[c.start_ns, c.end_ns]]
    rc, out, _ = _cli(capsys, "inspect", "--verify", fixed)  # whole itself, and says what its source lost
    assert rc == 0 and f"made from a damaged source: {len(held)} messages lost" in out


def test_damaged_chunk_holding_the_channel_records(killed, tmp_path, capsys):
    """The first chunk defines every channel: later chunks are still read, recovered and converted."""
    path, c, held = _damaged(tmp_path, killed, 0)
    _, _, written = killed
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", mio.TruncatedFileWarning)
        session = mio.Session(path)
        counts_left = session.count("mntes/t/counts/**")
    intact_counts = mio.Session(tmp_path / "intact.mcap", warn=False).count("mntes/t/counts/**")
    assert counts_left == intact_counts - sum(m.topic.startswith("mntes/t/counts/") for m in held) > 40

    fixed = tmp_path / "fixed.mcap"
    rc, out, err = _cli(capsys, "recover", path, fixed)
    assert rc == 0 and f"{written - len(held)} messages from" in out and f"LOST {len(held)} messages" in out
    assert "channels rebuilt from their payloads" in err and "mntes/t/counts/0/1" in err
    assert len(_messages(fixed)) == written - len(held)

    conv = tmp_path / "conv.mcap"
    rc, out, err = _cli(capsys, "convert", "-q", path, conv)
    assert rc == 0 and "input DAMAGED" in err
    final = out.strip().splitlines()[-1]
    assert f"1 damaged chunk(s), {len(held)} messages lost" in final
    power = mio.Session(conv, warn=False).count("mntes/t/power/**")
    assert power == counts_left  # every readable counts chunk converted
    meta = {m.name: m.data for m in mio.read_metadata(conv)}
    assert meta["mntes.damaged"]["messages_lost"] == str(len(held))


def test_a_chunk_cut_by_the_kill_is_damage_of_unknown_size(killed, tmp_path, capsys):
    data, chunks, _ = killed
    c = chunks[-1]
    path = tmp_path / "cut.mcap"
    path.write_bytes(data[: c.offset + c.length // 2])
    rc, out, err = _cli(capsys, "inspect", "--verify", path)
    assert rc == 2 and "every chunk verified" not in out
    assert f"damaged chunk at byte {c.offset}: an unknown number of messages" in out and "cut by the end" in out
    rc, out, _ = _cli(capsys, "recover", path, tmp_path / "fixed.mcap")
    assert rc == 0 and "1 chunk(s) of unknown size" in out
    # Cut exactly between chunks: nothing lost, nothing called damaged.
    (tmp_path / "clean.mcap").write_bytes(data[: c.offset])
    rc, out, err = _cli(capsys, "inspect", "--verify", tmp_path / "clean.mcap")
    assert rc == 0 and "UNFINISHED" in out and "every chunk verified" in out


# ---------------------------------------------------------------------------- full disk


@pytest.fixture
def small_disk(tmp_path):
    """A 2 MB tmpfs (skipped where mounting is not permitted), unmounted afterwards."""
    d = tmp_path / "disk"
    d.mkdir()
    res = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=2m", "tmpfs", str(d)], capture_output=True, text=True)
    if res.returncode != 0:
        pytest.skip(f"cannot mount a small tmpfs here: {res.stderr.strip() or res.returncode}")
    try:
        yield d
    finally:
        subprocess.run(["umount", "-l", str(d)], capture_output=True)


def _fill(disk: Path, leave_bytes: int) -> None:
    st = os.statvfs(disk)
    with open(disk / "filler", "wb") as f:
        f.write(b"\0" * max(0, st.f_bavail * st.f_frsize - leave_bytes))


def _run(*argv) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "mntes_stream", *map(str, argv)], capture_output=True, text=True,
                          timeout=120)


def _one_line_error(res) -> str:
    lines = res.stderr.strip().splitlines()
    assert res.returncode in (1, 2) and "Traceback" not in res.stderr, res.stderr
    assert len([x for x in lines if x.startswith("mntes-stream: error:")]) == 1, res.stderr
    return lines[-1]


def test_full_disk_is_one_line_and_leaves_no_file_that_looks_finished(killed, small_disk, tmp_path):
    data, _, written = killed
    src = tmp_path / "in.mcap"
    src.write_bytes(data)
    conv = tmp_path / "conv.mcap"
    assert _run("convert", "-q", src, conv).returncode == 0
    _fill(small_disk, 64 * 1024)
    for argv, out in ((("convert", "-q", src), small_disk / "c.mcap"),
                      (("recover", src), small_disk / "r.mcap"),
                      (("export", conv, "--compression", "none", "--json", "--out"), small_disk / "e.h5"),
                      (("export", conv, "--format", "toast", "--out"), small_disk / "toast"),
                      (("export", conv, "--format", "sotodlib", "--out"), small_disk / "so.h5")):
        res = _run(*argv, out)
        line = _one_line_error(res)  # never rc 139, never a traceback
        assert "No space left on device" in line, line
        assert sorted(p.name for p in small_disk.iterdir()) == ["filler"]  # nor OUT, nor OUT.partial


def test_recorder_writer_on_a_full_disk_says_what_the_file_holds(small_disk):
    from mcap_helpers import counts_payload

    from mntes_stream.errors import TransportError

    _fill(small_disk, 256 * 1024)
    w = mio.RotatingMcapWriter(small_disk, "rec", flush_interval_s=3600, rotate_s=0, rotate_bytes=0,
                               compression="none")
    with pytest.raises(TransportError) as err:
        for i in range(100_000):  # about 300 bytes a message: the disk is full long before
            w.write("mntes/t/counts/0/0", counts_payload(i), T0 + i)
            if i % 50 == 49:
                w.flush()
    msg = str(err.value)
    assert "No space left on device" in msg and "\n" not in msg
    said = w.messages
    assert f"In all: {said} messages" in msg and said > 0 and said % 50 == 0
    # Later writes (a recorder draining its queue) are counted, not written, and raise nothing: the caller
    # can close its sessions in order.
    w.write("mntes/t/counts/0/0", counts_payload(0), T0)
    w.flush()
    w.tick()
    assert w.messages == said and w.unwritten >= 1
    w.close()  # after the failure: closes the handle, raises nothing
    with contextlib.suppress(FileNotFoundError):
        (small_disk / "filler").unlink()  # room for recover's output
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", mio.TruncatedFileWarning)
        got = len(list(mio.iter_messages(small_disk / "rec-000001.mcap")))
    assert said <= got < said + 50  # the count said is what the file holds up to its last flush


def test_export_of_a_finished_file_with_a_damaged_chunk_marks_the_gap(killed, tmp_path, capsys):
    """A finished file (summary path): the damage is found on reading, said, and listed in the HDF5 file."""
    import h5py

    data, _, _ = killed
    (tmp_path / "in.mcap").write_bytes(data)
    conv = tmp_path / "conv.mcap"
    rc, _, _ = _cli(capsys, "convert", "-q", tmp_path / "in.mcap", tmp_path / "one_chunk.mcap")
    assert rc == 0
    with mio.McapFileWriter(conv) as w:  # the same, finished, in chunks of 20 messages
        for k, m in enumerate(_messages(tmp_path / "one_chunk.mcap")):
            w.write(m.topic, m.payload, m.log_time_ns)
            if k % 20 == 19:
                w.flush()
    chunks = sorted(index_file(conv).chunks, key=lambda c: c.offset)
    c = chunks[len(chunks) // 2]
    bad = bytearray(conv.read_bytes())
    bad[c.offset + c.length - 20] ^= 0xFF
    (tmp_path / "bad.mcap").write_bytes(bytes(bad))
    lost = len(_messages(conv)) - len(_messages(tmp_path / "bad.mcap"))
    assert lost > 0
    rc, out, err = _cli(capsys, "export", tmp_path / "bad.mcap", "--out", tmp_path / "p.h5", "--json")
    assert rc == 0, err
    doc = json.loads(out)
    assert rc == 0 and "input DAMAGED" in err and f"1 damaged chunk(s), {lost} messages lost" in doc["damaged"]
    assert doc["gap_samples"] > 0  # the power the chunk held is a hole: NaN + GAP
    with h5py.File(tmp_path / "p.h5") as f:
        assert json.loads(f.attrs["damaged_spans_ns"]) == [[c.start_ns, c.end_ns]]
        assert json.loads(f.attrs["damaged_chunks"])[0]["messages"] == lost
    rc, out, _ = _cli(capsys, "export", conv, "--out", tmp_path / "ok.h5", "--json")
    assert rc == 0 and "damaged" not in json.loads(out)
    with h5py.File(tmp_path / "ok.h5") as f:
        assert f.attrs["damaged"] == "" and json.loads(f.attrs["damaged_spans_ns"]) == []

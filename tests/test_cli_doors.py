"""Every door of the command line: bad input is one line on stderr and a non-zero exit, never a traceback.

Exit codes: 0 done, 2 an error said on purpose (bad config, arguments, files, data, a path the command cannot
use) or an argparse usage error, 1 the command failed at its work (an I/O error, a full disk, a service dying
too often), 130 Ctrl-C, 141 the reader of stdout went away.
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

CLI = [sys.executable, "-m", "mntes_stream"]


def _run(*args, timeout=180, **kw):
    return subprocess.run([*CLI, *map(str, args)], capture_output=True, text=True, timeout=timeout, **kw)


def _one_line_error(res) -> str:
    assert "Traceback" not in res.stderr, res.stderr
    lines = [line for line in res.stderr.strip().splitlines() if line]
    assert len(lines) >= 1
    return lines[-1]


def test_up_rejects_an_unknown_kind_in_one_line():
    res = _run("up", "--kind", "tabel", "--duration", "1")
    assert res.returncode == 2
    assert "invalid choice: 'tabel'" in _one_line_error(res)


def test_up_into_an_unusable_directory_is_one_line(tmp_path):
    res = _run("up", "--out", "/proc/nope", "--duration", "1")
    assert res.returncode == 2  # a path the user gave that cannot be used: bad input, as a missing input file is
    line = _one_line_error(res)
    assert line.startswith("mntes-stream: error:") and "/proc/nope" in line
    assert len(res.stderr.strip().splitlines()) == 1


def test_up_json_is_one_document_and_ctrl_c_during_start_up_is_130(tmp_path):
    out = tmp_path / "up"
    res = _run("up", "--json", "--duration", "3", "--modules", "1", "--channels", "4", "--out", out, timeout=300)
    assert res.returncode == 0, res.stderr
    doc = json.loads(res.stdout)  # stdout holds the JSON document and nothing else
    assert doc["ok"] and not doc["interrupted"]
    conv, rec = doc["services"]["converter"], doc["services"]["recorder"]
    assert conv["chunks_converted"] > 0 and conv["chunks_lost"] == 0 and len(rec["files"]) == 1
    assert "mntes-stream up:" in res.stderr and "done:" in res.stderr  # the lines went to stderr
    # The folder up wrote is a recording for every command that reads one.
    assert _run("inspect", out).returncode == 0
    res = _run("export", out, "--out", tmp_path / "x.h5", "--json")
    assert res.returncode == 0 and json.loads(res.stdout), res.stderr
    res = _run("convert", out, tmp_path / "re.mcap", "--json")
    assert res.returncode == 0 and (tmp_path / "re.mcap").stat().st_size > 0, res.stderr
    res = _run("replay", out, "--afap", "--json", "-l", "tcp/127.0.0.1:0", "--no-multicast-scouting")
    assert res.returncode == 0 and json.loads(res.stdout)["messages"] > 0, res.stderr
    first_files = set((out / "recordings").glob("*.mcap"))
    # Ctrl-C while the services start: clean stop, exit code 130, a summary of this run only.
    proc = subprocess.Popen([*CLI, "up", "--duration", "0", "--modules", "1", "--channels", "4", "--out", str(out)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:  # the recorder (first service) is starting: its file appears
            if set((out / "recordings").glob("*.mcap")) - first_files:
                break
            time.sleep(0.05)
        proc.send_signal(signal.SIGINT)
        stdout, stderr = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 130, stderr
    assert "Traceback" not in stderr and "KeyboardInterrupt" not in stderr, stderr
    done = [line for line in stdout.splitlines() if line.startswith("done")]
    assert done and "(interrupted)" in done[0], stdout
    new_files = set((out / "recordings").glob("*.mcap")) - first_files
    assert f"into {len(new_files)} MCAP file(s)" in done[0]  # not the first run's file too


def _many_topics(path: Path, n: int) -> None:
    from mcap_helpers import hk_payload

    from mntes_stream.io.mcap import McapFileWriter

    with McapFileWriter(path) as w:
        for i in range(n):
            w.write(f"mntes/lab/hk/sensor{i:05d}", hk_payload(i, setup="lab"), 1_000 + i)


def test_inspect_into_a_closed_pipe_is_quiet(tmp_path):
    rec = tmp_path / "many.mcap"
    _many_topics(rec, 4000)  # > 64 KiB of output: the writer meets the closed pipe
    res = subprocess.run(f"{sys.executable} -m mntes_stream inspect {rec} | head -n 2", shell=True,
                         capture_output=True, text=True, timeout=120)
    assert len(res.stdout.splitlines()) == 2
    assert "Traceback" not in res.stderr and "BrokenPipe" not in res.stderr, res.stderr


def test_a_missing_extra_names_it(tmp_path):
    code = (
        "import sys\n"
        "class Block:\n"
        "    def find_spec(self, name, path=None, target=None):\n"
        "        if name.split('.')[0] == 'aiohttp':\n"
        "            raise ModuleNotFoundError(\"No module named 'aiohttp'\")\n"
        "sys.meta_path.insert(0, Block())\n"
        "from mntes_stream.cli import main\n"
        "sys.exit(main(['monitor', '--duration', '1', '--port', '0']))\n"
    )
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert res.returncode == 2
    line = _one_line_error(res)
    assert "pip install 'mntes-stream[monitor]'" in line


@pytest.mark.parametrize("args, expect", [
    (["replay", "--afap"], "nothing to replay"),
    (["serve", "--config", "services/recorder.toml", "--set", "recorder.flush_interval_s=-1"],
     "command line --set [recorder] flush_interval_s: expected a number (s) > 0, got -1"),
    (["serve", "--config", "services/recorder.toml", "--set", "nonsense"], "expected TABLE.KEY=VALUE"),
    (["record", "--flush-s", "0", "--duration", "1"], "argument --flush-interval-s/--flush-s: expected a number (s) > 0"),
    (["serve", "--config", "services/converter.toml", "--cfg", "no-colon"], "expected KEY:VALUE"),
    (["simulate", "--out", "x.mcap", "-e", "tcp/127.0.0.1:1"], "give either --out FILE.mcap or zenoh endpoints"),
])
def test_bad_arguments_are_one_line(args, expect):
    res = _run(*args)
    assert res.returncode == 2, res.stderr
    assert expect in _one_line_error(res)

"""The README stays a front door (at most 300 lines) and no relative link in it or docs/ is dead."""

from __future__ import annotations

import re
import shlex
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README_MAX_LINES = 300
# [text](target) and ![alt](target); the target ends at whitespace or ')' (no titles used here).
_LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)\)")
_FENCE = re.compile(r"^```.*?^```", re.S | re.M)


def relative_links(md: Path) -> list[str]:
    """Relative link targets of a Markdown file, outside code blocks, without their #anchor.

    >>> import tempfile, pathlib
    >>> p = pathlib.Path(tempfile.mkdtemp()) / "a.md"
    >>> _ = p.write_text("[x](docs/a.md#b) [y](https://e.org) ![z](img.png)\\n```\\n[no](q.md)\\n```\\n[w](#top)")
    >>> relative_links(p)
    ['docs/a.md', 'img.png']
    """
    text = _FENCE.sub("", md.read_text())
    out = []
    for target in _LINK.findall(text):
        if re.match(r"^[a-z][a-z0-9+.-]*:", target, re.I) or target.startswith("#"):
            continue  # a URL (https:, mailto:) or an anchor in the same page
        out.append(target.split("#", 1)[0])
    return out


def test_readme_is_at_most_300_lines():
    n = len((ROOT / "README.md").read_text().splitlines())
    assert n <= README_MAX_LINES, f"README.md has {n} lines; move detail to a docs/ topic page"


def test_readme_starts_with_the_install_and_test_commands():
    """The first code block: set up + `up`, then the full suite with every extra (what .ci/run runs)."""
    text = (ROOT / "README.md").read_text()
    block = text.split("```bash\n", 1)[1].split("```", 1)[0]
    commands = [ln for ln in block.splitlines() if ln.strip() and not ln.lstrip().startswith("#")]
    assert len(commands) == 2, commands
    setup, tests = commands
    assert "pip install" in setup and "-e ." in setup and "[" not in setup.split("-e ", 1)[1].split()[0]
    assert setup.rstrip().endswith("mntes-stream up")
    assert "[all,test]" in tests and tests.endswith("-m pytest -q")
    # .ci/run runs each part of it, in order, as a line of its own or together (it may do other set-up between).
    ci = [ln.strip() for ln in (ROOT / ".ci" / "run").read_text().splitlines() if not ln.lstrip().startswith("#")]
    at = [next((i for i, ln in enumerate(ci) if part in ln), None) for part in tests.split(" && ")]
    assert None not in at and at == sorted(at), f".ci/run does not run the README's test command: {tests}"
    assert sum("pytest" in ln for ln in ci) == 1, "CI runs one test command, the README's"


def test_slow_list_names_existing_test_files():
    """tests/slow_tests.txt (the fast subset's exclusions) follows renamed and deleted test files."""
    listed = {ln.split("#", 1)[0].strip().split("::", 1)[0]
              for ln in (ROOT / "tests" / "slow_tests.txt").read_text().splitlines()} - {""}
    missing = sorted(f for f in listed if not (ROOT / f).exists())
    assert not missing, f"tests/slow_tests.txt names files that do not exist: {missing}"


def test_every_relative_link_in_readme_and_docs_resolves():
    pages = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md")), ROOT / "benchmarks" / "README.md"]
    dead = [f"{md.relative_to(ROOT)}: {t}" for md in pages for t in relative_links(md)
            if not (md.parent / t).exists()]
    assert not dead, "dead links:\n" + "\n".join(dead)


VENV = ".venv/bin/"  # the README's one spelling of the venv's commands (its first block makes .venv)


def _quick_start_lines() -> list[str]:
    """The `$ ...` lines of the README's "Quick start", in order, without their comments."""
    text = (ROOT / "README.md").read_text()
    section = text.split("\n## Quick start\n", 1)[1].split("\n## ", 1)[0]
    return [ln[2:].split("  #", 1)[0].strip() for ln in section.splitlines() if ln.startswith("$ ")]


def _quick_start_commands() -> list[str]:
    """The `$ .venv/bin/mntes-stream ...` lines of the README's "Quick start", as `mntes-stream ...`."""
    return [ln[len(VENV):] for ln in _quick_start_lines() if ln.startswith(VENV + "mntes-stream ")]


def test_quick_start_uses_one_venv_spelling():
    """Issue 34: `.venv/bin/...` then bare `pip`: a user without an activated venv installed the monitor extra
    into another Python. Every command of the Quick start is the venv's, as the README's first block makes it."""
    lines = _quick_start_lines()
    assert lines and all(ln.startswith(VENV) for ln in lines), lines
    assert any(ln.startswith(VENV + "pip install") and "[monitor]" in ln for ln in lines), lines


@pytest.mark.slow
def test_readme_quick_start_runs_as_written(tmp_path, monkeypatch, capsys):
    """`up`, the monitor attached with both of the ports `up` prints, then inspect and export of the recording."""
    cmds = _quick_start_commands()
    assert [c.split()[1] for c in cmds] == ["up", "monitor", "monitor", "inspect", "export"], cmds
    exe = [sys.executable, "-m", "mntes_stream"]
    up = subprocess.Popen(exe + cmds[0].split()[1:], cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                          text=True)
    try:
        ports = None
        deadline = time.monotonic() + 60
        while ports is None and time.monotonic() < deadline:
            line = up.stdout.readline()
            assert line, "up ended before it printed its ports: " + up.stderr.read()[-2000:]
            m = re.search(r"converter :(\d+), source :(\d+)", line)
            ports = m and m.groups()
        assert ports, "up printed no ports within 60 s"
        line = up.stdout.readline()
        assert line.startswith("  monitor, from a second terminal: "), line
        pasted = line.split(": ", 1)[1].strip()
        while time.monotonic() < deadline:  # as a user would: attach once power flows
            line = up.stdout.readline()
            assert line, "up ended early: " + up.stderr.read()[-2000:]
            if re.search(r"power chunks\s+[1-9]", line):
                break
        else:
            raise AssertionError("no power within 60 s of up's start")
        # up prints the monitor's command to paste (issue 34): the README's, with this run's ports and program.
        printed = shlex.split(pasted)
        assert printed[:len(exe)] == exe, pasted
        readme = cmds[1].replace("39175", ports[0]).replace("49485", ports[1]).split()
        assert printed[len(exe):] == readme[1:], (pasted, cmds[1])
        text = cmds[2].replace("39175", ports[0]).replace("49485", ports[1]).split()
        assert text[1:] == [*printed[len(exe):len(exe) + 1], "--text", "--duration", "5", *printed[len(exe) + 1:]]
        out = subprocess.run(printed[:len(exe) + 1] + text[2:], cwd=tmp_path, capture_output=True, text=True,
                             timeout=60)
        assert out.returncode == 0, out.stderr[-2000:]
        # Power from the converter's port and housekeeping from the source's: both connections carried data.
        assert re.search(r"^converter\s+\d", out.stdout, re.M), out.stdout[-2000:]
        assert re.search(r"housekeeping: t_bath \d", out.stdout), out.stdout[-2000:]
    finally:
        up.send_signal(signal.SIGINT)
        rest, err = up.communicate(timeout=60)
    assert up.returncode == 130, err[-2000:]
    assert re.search(r"converter: received (\d+) chunks: converted \1; lost 0 of \1", rest), rest
    # inspect and export through the command's own main in this process (two interpreter starts less).
    from mntes_stream.cli import main

    monkeypatch.chdir(tmp_path)
    capsys.readouterr()
    assert main(cmds[3].split()[1:]) == 0
    inspected = capsys.readouterr().out
    assert re.search(r"received (\d+) chunks: converted \1; lost 0 of \1", inspected), inspected
    assert main(cmds[4].split()[1:]) == 0
    h5py = pytest.importorskip("h5py")
    with h5py.File(tmp_path / "power.h5") as f:
        assert sorted(k for k in f if k.startswith("lab_")) == [f"lab_b0m{m}" for m in range(4)]  # up's 4 modules
        assert f["lab_b0m0"]["tod"].shape[0] == 64
        # docs/feeds.md: table identities are sha256 hex digests (no "sha256:" prefix, issue 34).
        import json

        ids = json.loads(f["lab_b0m0"].attrs["table_identities"])
        assert ids and all(re.fullmatch(r"[0-9a-f]{64}", i) for i in ids), ids

"""The command's start-up stays light: `mntes-stream --help` and `mntes-stream convert --help` build their
parsers without importing numba, zenoh, mcap or numpy (issue 23: every command's parser built with them took
0.75 CPU s before any command ran). A fresh interpreter, as a user's shell starts one; no timing, only what is
imported."""

from __future__ import annotations

import json
import subprocess
import sys

HEAVY = ("numba", "zenoh", "mcap", "numpy")

_PROBE = """
import contextlib, io, json, sys
from mntes_stream.cli import main
seen = {}
for argv in (["--help"], ["convert", "--help"]):
    with contextlib.redirect_stdout(io.StringIO()), contextlib.suppress(SystemExit):
        main(argv)
    seen[" ".join(argv)] = sorted({m.split(".")[0] for m in sys.modules} & set(HEAVY))
print(json.dumps(seen))
"""


def test_help_imports_no_heavy_module():
    out = subprocess.run([sys.executable, "-c", f"HEAVY = {HEAVY!r}\n{_PROBE}"], capture_output=True, text=True,
                         check=True, timeout=60)
    seen = json.loads(out.stdout)
    assert seen == {"--help": [], "convert --help": []}, (
        f"the CLI's start-up imports heavy modules: {seen} (import them inside the command's run function, or "
        "add a command's arguments through cli._common.arguments)")


def test_a_command_still_gets_its_arguments_when_run():
    # The lazy parser: `record --help` shows the recorder's settings flags, built from its settings class.
    out = subprocess.run([sys.executable, "-m", "mntes_stream", "record", "--help"], capture_output=True, text=True,
                         check=True, timeout=60)
    assert "--rotate-mb" in out.stdout and "--compression" in out.stdout

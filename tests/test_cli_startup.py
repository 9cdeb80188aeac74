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


_SERVE_PROBE = """
import contextlib, io, json, sys
from mntes_stream.cli import main
from mntes_stream.service.registry import ENTRIES
with contextlib.redirect_stderr(io.StringIO()):
    rc = main(["serve", "--config", "no-such.toml"])
others = sorted(n for n, e in ENTRIES.items() if e.partition(":")[0] in sys.modules)
with contextlib.redirect_stdout(io.StringIO()) as out, contextlib.suppress(SystemExit):
    main(["serve", "--help"])
print(json.dumps({"rc": rc, "imported": others, "help_lists_monitor": "[monitor] " in out.getvalue()}))
"""


def test_serve_imports_no_other_service_until_its_help_is_asked_for():
    # `serve` listed every service in its description, which imported every service's module (0.9 CPU s on a
    # slow VM) before the one it runs; a CI run interrupted a source still doing so (rc -2, a traceback).
    out = subprocess.run([sys.executable, "-c", _SERVE_PROBE], capture_output=True, text=True, check=True, timeout=60)
    assert json.loads(out.stdout) == {"rc": 2, "imported": [], "help_lists_monitor": True}


_INTERRUPT_PROBE = """
import os, signal, sys
from mntes_stream.cli import _common, main
real = _common.CommandParser.filled

def filled(self):  # Ctrl-C (a real SIGINT) while the command's arguments are still being built
    os.kill(os.getpid(), signal.SIGINT)
    return real(self)

_common.CommandParser.filled = filled
sys.exit(main(["serve", "--config", "services/source.toml"]))
"""


def test_an_interrupt_while_a_command_starts_exits_130_without_a_traceback():
    out = subprocess.run([sys.executable, "-c", _INTERRUPT_PROBE], capture_output=True, text=True, timeout=60)
    assert (out.returncode, out.stderr) == (130, "")

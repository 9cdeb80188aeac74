"""The ``mntes-stream`` command.

Each module in this package that defines ``register(subparsers)`` adds its
subcommands; modules import their heavy dependencies inside the handlers, and
a command whose arguments need a heavy module (a service's settings class)
adds them through ``_common.arguments``, when that command is the one run, so
``mntes-stream --help`` and every command import only what they use
(tests/test_cli_startup.py).
"""

from __future__ import annotations

import argparse
import errno
import importlib
import os
import pkgutil
import sys
import textwrap

from mntes_stream import __version__
from mntes_stream.cli._common import CommandParser, OneLineParser
from mntes_stream.errors import MntesError

# `mntes-stream --help` lists the commands in these groups, in this order (docs/cli.md). A command not named
# here is listed under "other" (tests/test_cli_grammar.py fails on it: place it in a group).
GROUPS: dict[str, tuple[str, ...]] = {
    "operate": ("up", "serve", "config", "router", "ps", "monitor", "foxglove", "g3-bridge", "dfmux-bridge",
                "ocs-bridge"),
    "record and replay": ("record", "replay", "inspect", "recover", "convert", "transcode"),
    "export": ("export",),
    "calibrate and validate": ("calib", "params", "tables", "model", "validate", "leakage", "noise"),
    "develop": ("simulate", "bench", "cache"),
}


def _grouped(sub) -> str:
    """The commands' one-line helps, grouped as :data:`GROUPS` says."""
    helps = {a.dest: a.help or "" for a in sub._choices_actions}
    placed = {c for cs in GROUPS.values() for c in cs}
    lines = []
    groups = {**GROUPS, "other": tuple(sorted(c for c in helps if c not in placed))}
    width = max(map(len, helps), default=8) + 2
    for title, names in groups.items():
        names = [n for n in names if n in helps]
        if not names:
            continue
        lines += ["", f"{title}:"]
        for n in names:
            text = textwrap.wrap(helps[n], 100 - width - 2) or [""]
            lines.append(f"  {n:<{width}}{text[0]}")
            lines.extend(f"  {'':<{width}}{t}" for t in text[1:])
    return "\n".join(lines[1:])


def build_parser(lazy: bool = False) -> argparse.ArgumentParser:
    """The command's parser: every command with every argument, or (``lazy``) each command's arguments
    added when it parses or prints its help (what :func:`main` runs: one command's arguments built)."""
    parser = OneLineParser(
        prog="mntes-stream",
        usage="mntes-stream [-h] [--version] COMMAND ...",
        description="Real-time MNTES conversion of DfMux TES readout to optical power.",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="`mntes-stream COMMAND --help` describes a command; docs/cli.md: the flags every command shares, "
               "exit codes (0 done, 1 failed at its work, 2 bad arguments, input, config or path, 130 interrupted).",
    )
    parser.add_argument("--version", action="version", version=f"mntes-stream {__version__}")
    # prog: each command's own is "mntes-stream up", not the whole usage line before it.
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", title="commands", parser_class=CommandParser,
                                prog="mntes-stream")
    for info in sorted(pkgutil.iter_modules(__path__), key=lambda m: m.name):
        if info.name.startswith("_"):
            continue
        module = importlib.import_module(f"{__name__}.{info.name}")
        register = getattr(module, "register", None)
        if register is not None:
            register(sub)
    sub.help = argparse.SUPPRESS  # the flat list; the grouped one is the description below
    parser.description += "\n\n" + _grouped(sub)
    if not lazy:
        for command in sub.choices.values():
            command.filled()
    return parser


def main(argv: list[str] | None = None) -> int:
    try:
        return _main(argv)
    except KeyboardInterrupt:  # also while a command is still starting (its imports, its arguments): no traceback
        return 130


def _main(argv: list[str] | None) -> int:
    parser = build_parser(lazy=True)
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    from mntes_stream.service.heap import own_process, pad_heap

    pad_heap()  # commands move payloads too (convert, record, bench): see service.heap
    if argv is None:  # the executable, not a caller's process (a test): a service's setup may be frozen there
        own_process()
    import warnings

    # A warning is one line, as an error is (Python's own format adds the file, line and source line).
    warnings.showwarning = lambda message, category, filename, lineno, file=None, line=None: print(
        f"mntes-stream: warning: {message}", file=sys.stderr, flush=True)
    try:
        return int(args.func(args) or 0)
    except MntesError as exc:  # said on purpose: bad config, input or data, a dead endpoint
        return _error(exc, 2)
    except BrokenPipeError:  # e.g. `mntes-stream inspect ... | head`: the reader has gone
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 141
    except OSError as exc:
        where = f": {exc.filename}" if exc.filename else ""
        # A path the user gave that cannot be used is bad input (2), as a missing input file is; the
        # machine failing the command at its work (a full disk, an I/O error) is 1.
        return _error(f"{exc.strerror or exc}{where}", 2 if exc.errno in _BAD_PATH else 1)


_BAD_PATH = frozenset({errno.ENOENT, errno.ENOTDIR, errno.EISDIR, errno.EACCES, errno.EPERM, errno.EROFS, errno.EEXIST,
                       errno.ENAMETOOLONG, errno.ELOOP})


def _error(what, rc: int) -> int:
    """One line on stderr (a message from below, e.g. zenoh's, may hold newlines), the exit code back."""
    print(f"mntes-stream: error: {' '.join(str(what).split())}", file=sys.stderr)
    return rc


if __name__ == "__main__":
    sys.exit(main())

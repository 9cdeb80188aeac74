"""The ``mntes-stream`` command.

Each module in this package that defines ``register(subparsers)`` adds its
subcommands; modules import their heavy dependencies inside the handlers so
``mntes-stream --help`` stays fast.
"""

from __future__ import annotations

import argparse
import importlib
import os
import pkgutil
import sys

from mntes_stream import __version__
from mntes_stream.errors import MntesError


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="mntes-stream",
        description="Real-time MNTES conversion of DfMux TES readout to optical power.",
    )
    parser.add_argument("--version", action="version", version=f"mntes-stream {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for info in sorted(pkgutil.iter_modules(__path__), key=lambda m: m.name):
        if info.name.startswith("_"):
            continue
        module = importlib.import_module(f"{__name__}.{info.name}")
        register = getattr(module, "register", None)
        if register is not None:
            register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except MntesError as exc:  # said on purpose: bad config, input or data, a dead endpoint
        return _error(exc, 2)
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:  # e.g. `mntes-stream inspect ... | head`: the reader has gone
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 141
    except OSError as exc:  # a file or directory the command was told to use
        where = f": {exc.filename}" if exc.filename else ""
        return _error(f"{exc.strerror or exc}{where}", 1)


def _error(what, rc: int) -> int:
    """One line on stderr, the exit code back."""
    print(f"mntes-stream: error: {what}", file=sys.stderr)
    return rc


if __name__ == "__main__":
    sys.exit(main())

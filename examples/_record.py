"""Shared by the framework examples: a recording (``mntes-stream up``, or ``--session``), exported with ``--format``.

Every failure is one line on stderr and exit code 2 (``fail``): an ``up``
that recorded nothing, an export that refused the session, a recording
without usable power.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import numpy as np

# A detector whose power is usable for less than this share of an observation's samples is left out: a
# latched channel that comes out of latch now and then (98.6 % unusable over `up`'s default 60 s) would
# otherwise leave no span where every kept detector is usable.
MIN_USABLE_FRACTION = 0.5


def fail(message: str) -> None:
    """One line on stderr, exit code 2 (as the ``mntes-stream`` command does for bad input)."""
    print(f"{Path(sys.argv[0]).name}: error: {message}", file=sys.stderr)
    sys.exit(2)


def arguments(description: str) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=description)
    p.add_argument("--work", default="mntes-example", help="directory for the recording and the export")
    p.add_argument("--session", help="an existing recording (MCAP file or directory, e.g. mntes-up/recordings "
                                      "as `mntes-stream up` writes it) instead of running `up`")
    p.add_argument("--duration", type=float, default=15.0, help="seconds of `up` to record (default 15)")
    p.add_argument("--json", action="store_true", help="print the result as one JSON document")
    args = p.parse_args()
    if args.session is not None:  # checked before a framework is imported (seconds)
        session = Path(args.session)
        if not session.exists():
            fail(f"--session {session}: no such file or directory")
        if session.is_dir() and not any(session.glob("*.mcap")):
            fail(f"--session {session}: no MCAP file in it (did `mntes-stream up` record anything?)")
    return args


def _mntes(*args: str) -> None:
    """Run ``mntes-stream ARGS``; its own one-line error (last stderr line) on failure."""
    res = subprocess.run([sys.executable, "-m", "mntes_stream", *args], stdout=subprocess.DEVNULL,
                         stderr=subprocess.PIPE, text=True)
    if res.returncode != 0:
        last = (res.stderr.strip().splitlines() or [f"exit code {res.returncode}"])[-1]
        fail(f"mntes-stream {args[0]} failed: {last}")


def record_and_export(args: argparse.Namespace, fmt: str) -> Path:
    """Record (unless ``--session``) and export with ``--format fmt``; returns the export's path."""
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    session = args.session
    if session is None:
        # 2 modules x 8 channels of the array simulator through the converter into MCAP, for --duration s.
        _mntes("up", "--duration", str(args.duration), "--modules", "2", "--channels", "8", "--out",
               str(work / "up"), "-q")
        session = str(work / "up" / "recordings")
        if not list(Path(session).glob("*.mcap")):
            fail(f"`mntes-stream up --duration {args.duration:g}` recorded nothing in {session}: "
                 "a longer --duration gives the services time to start")
    out = work / f"export-{fmt}{'.h5' if fmt == 'sotodlib' else ''}"
    _mntes("export", session, "--format", fmt, "--out", str(out), "--overwrite", "--json")
    return out


def usable_detectors(unusable: np.ndarray) -> np.ndarray:
    """Rows of ``unusable`` (detectors x samples, True: no usable power) usable often enough to keep."""
    if unusable.shape[1] == 0:
        return np.zeros(unusable.shape[0], dtype=bool)
    return (~unusable).mean(axis=1) >= MIN_USABLE_FRACTION


def longest_run(ok: np.ndarray) -> tuple[int, int]:
    """``(start, stop)`` of the longest run of True in ``ok`` ((0, 0) if none)."""
    edges = np.flatnonzero(np.diff(np.concatenate([[0], ok.astype(np.int8), [0]])))
    if edges.size == 0:
        return 0, 0
    starts, stops = edges[0::2], edges[1::2]
    k = int(np.argmax(stops - starts))
    return int(starts[k]), int(stops[k])


def report(args: argparse.Namespace, result: dict) -> None:
    if args.json:
        print(json.dumps(result, indent=2))
    else:
        for k, v in result.items():
            print(f"{k}: {v}")

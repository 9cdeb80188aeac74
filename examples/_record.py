"""Shared by the framework examples: a short recording with ``mntes-stream up``, exported with ``--format``."""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path


def arguments(description: str) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=description)
    p.add_argument("--work", default="mntes-example", help="directory for the recording and the export")
    p.add_argument("--session", help="an existing recording (MCAP file or directory) instead of running `up`")
    p.add_argument("--duration", type=float, default=5.0, help="seconds of `up` to record (default 5)")
    p.add_argument("--json", action="store_true", help="print the result as one JSON document")
    return p.parse_args()


def _mntes(*args: str) -> None:
    subprocess.run([sys.executable, "-m", "mntes_stream", *args], check=True, stdout=subprocess.DEVNULL)


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
    out = work / f"export-{fmt}{'.h5' if fmt == 'sotodlib' else ''}"
    _mntes("export", session, "--format", fmt, "--out", str(out), "--overwrite", "--json")
    return out


def report(args: argparse.Namespace, result: dict) -> None:
    if args.json:
        print(json.dumps(result, indent=2))
    else:
        for k, v in result.items():
            print(f"{k}: {v}")

"""Benchmarks behind ``mntes-stream bench NAME``.

Each module ``mntes_stream.bench.<name>`` defines ``HELP`` (one line),
``add_arguments(parser)`` and ``run(args) -> dict`` (the JSON result). Speed
and memory targets live here and in ``benchmarks/``, never in timed unit tests.
"""

import os
import platform


def machine() -> dict:
    """Where a figure was measured (goes into every benchmark's JSON)."""
    info = {"python": platform.python_version(), "machine": platform.machine(), "cpus": os.cpu_count()}
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    info["cpu"] = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    return info

"""G3 work in a child process that never loads so3g (``export RUN.g3 --format toast``).

so3g and toast need their shared libraries before spt3g's, and so3g brings
its own older spt3g, which cannot read DfMux housekeeping written by spt3g
1.0.2. A process that needs a framework therefore never reads G3 itself: it
calls :func:`run`, which starts ``python -m mntes_stream.g3.isolated TASK
JSON`` with so3g/toast/sotodlib refused, and gets the task's JSON result back
(the data travel as a file: an MCAP recording the parent reads with its own
code).
"""

from __future__ import annotations

import json
import subprocess
import sys

from mntes_stream.errors import MntesError, SchemaError


def _g3_to_mcap(inputs, output, params, setup="lab") -> dict:
    from mntes_stream.g3.files import g3_to_mcap
    from mntes_stream.g3.runtime import spt3g_in_use

    stats = g3_to_mcap(inputs, output, params=params, setup=setup)
    return {"output": str(output), "power_chunks": stats.power_chunks, "spt3g": spt3g_in_use()}


def _positions(path) -> dict:
    from mntes_stream.g3.focal_plane import positions_from_g3

    return {"positions": {d: list(map(float, v)) for d, v in positions_from_g3(path).items()}}


TASKS = {"g3_to_mcap": _g3_to_mcap, "positions": _positions}


def run(task: str, **kwargs) -> dict:
    """Run ``task`` (a key of :data:`TASKS`) in a child process on spt3g 1.0.2; its JSON result.

    Raises
    ------
    MntesError
        The child's one-line error (a bad file, a missing extra), or its exit status.
    """
    if task not in TASKS:
        raise MntesError(f"unknown isolated G3 task {task!r}")
    p = subprocess.run([sys.executable, "-m", "mntes_stream.g3.isolated", task, json.dumps(kwargs, default=str)],
                       capture_output=True, text=True)
    if p.returncode != 0:
        lines = [ln for ln in p.stderr.splitlines() if ln.strip()]
        why = lines[-1].removeprefix("mntes-stream: error: ") if lines else f"exit status {p.returncode}"
        raise SchemaError(f"G3 reader process ({task}): {why}", "g3_child")
    return json.loads(p.stdout.splitlines()[-1])


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    from mntes_stream.g3.runtime import RefuseAfterSpt3g

    sys.meta_path.insert(0, RefuseAfterSpt3g())  # before anything could load so3g's spt3g
    try:
        task, kwargs = argv[0], json.loads(argv[1])
        out = TASKS[task](**kwargs)
    except MntesError as exc:
        print(f"mntes-stream: error: {exc}", file=sys.stderr)
        return 2
    except RuntimeError as exc:  # spt3g's own read errors
        print(f"mntes-stream: error: spt3g: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:
        print(f"mntes-stream: error: {exc.strerror or exc}: {exc.filename or ''}", file=sys.stderr)
        return 1
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())

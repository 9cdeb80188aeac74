"""The converter's checkpoint: each stream's newest sequence number on disk, so a restart knows what it missed.

Written with every status (and at a clean stop) to the ``checkpoint`` file
of ``[converter]``, atomically (a new file renamed over the old one: a
converter killed mid-write leaves the previous checkpoint whole). At start
the converter continues its streams from it
(:meth:`~mntes_stream.pipeline.pipeline.ConverterPipeline.resume_sequences`):
each stream's first chunk then says how many chunks were published while no
converter ran, counted in the status (``chunks_lost``), the heartbeat
(``chunks_missed_while_down``) and said once per stream in the log and
``last_error``. Chunks received but not yet converted when the process was
killed are not counted (at most ``hk_wait_s`` of data).

A status's checkpoint also keeps each stream's number as of the status
before (``floor``): the power of the chunks converted just before a status
is queued in zenoh when the checkpoint is written, and a converter killed
then (SIGKILL) never sends it. Only what the sources' history gives again
at or below the floor is dropped as a duplicate on restart; newer chunks
from it are converted again (their power twice at worst, never lost),
while what was missed is still counted from the newest number. A
restarted converter's first floor is the one it loaded (killed again
before its second status, it claims no less and no more). The
checkpoint of a clean stop, whose power was sent, has no floor: its
numbers are the floor.

Format (JSON; ``floor`` optional, a stream absent from it had none)::

    {"schema": "mntes-converter-checkpoint", "version": 1, "setup": "lab", "name": "converter",
     "t_ns": 1700000000000000000, "streams": [[board, module, seq, t_first_ns], ...],
     "floor": [[board, module, seq, t_first_ns], ...]}
"""

from __future__ import annotations

import json
import logging
import os
import tempfile
import time
from pathlib import Path

__all__ = ["CHECKPOINT_SCHEMA", "load_checkpoint", "save_checkpoint"]

log = logging.getLogger("mntes_stream.converter")

CHECKPOINT_SCHEMA = "mntes-converter-checkpoint"
_INT64 = (-(1 << 63), (1 << 63) - 1)


def save_checkpoint(path: str, setup: str, name: str, state: dict, floor: dict | None = None) -> None:
    """Write ``state`` (``pipeline.sequence_state()``) to ``path`` atomically; a failure is logged, never raised.

    ``floor``: the state as of the previous status (see the module docstring); None: ``state`` itself."""
    doc = {"schema": CHECKPOINT_SCHEMA, "version": 1, "setup": setup, "name": name, "t_ns": time.time_ns(),
           "streams": [[b, m, int(seq), int(t)] for (b, m), (seq, t) in sorted(state.items())]}
    if floor is not None:
        doc["floor"] = [[b, m, int(seq), int(t)] for (b, m), (seq, t) in sorted(floor.items())]
    target = Path(path)
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=".checkpoint-", dir=target.parent)
        try:
            with os.fdopen(fd, "w") as f:
                json.dump(doc, f)
            os.replace(tmp, target)
        except BaseException:
            os.unlink(tmp)
            raise
    except OSError as exc:
        log.warning("cannot write the checkpoint %s: %s", path, exc)


def load_checkpoint(path: str, setup: str, name: str) -> tuple[dict, int] | None:
    """``(state, t_ns)`` from ``path`` when it is this converter's (setup and name), else None (said why, once).

    ``state``: ``(board, module) -> (seq, t_first_ns)``, or ``(seq, t_first_ns, floor_seq, floor_t_ns)``
    where the checkpoint has a floor (``floor_seq`` -1: the stream had none), as
    ``ConverterPipeline.resume_sequences`` takes it."""
    try:
        doc = json.loads(Path(path).read_text())
    except FileNotFoundError:
        return None
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        log.warning("checkpoint %s unreadable (%s): starting without it", path, exc)
        return None
    try:
        if not isinstance(doc, dict) or doc.get("schema") != CHECKPOINT_SCHEMA or doc.get("version") != 1:
            raise ValueError("not a converter checkpoint (version 1)")
        if (doc.get("setup"), doc.get("name")) != (setup, name):
            raise ValueError(f"it is converter {doc.get('name')!r} of setup {doc.get('setup')!r}")
        state = _streams(doc["streams"])
        if "floor" in doc:
            floor = _streams(doc["floor"])
            state = {k: (seq, t, *floor.get(k, (-1, -1))) for k, (seq, t) in state.items()}
        t_ns = doc["t_ns"]
        if type(t_ns) is not int:
            raise ValueError("t_ns is not an integer")
    except (KeyError, TypeError, ValueError) as exc:
        log.warning("checkpoint %s not used: %s", path, exc)
        return None
    return state, t_ns


def _streams(entries) -> dict:
    """``[[board, module, seq, t_first_ns], ...]`` checked, as ``(board, module) -> (seq, t_first_ns)``."""
    if not isinstance(entries, list):
        raise ValueError("streams is not a list")
    out = {}
    for entry in entries:
        if (not isinstance(entry, list) or len(entry) != 4
                or not all(type(v) is int and _INT64[0] <= v <= _INT64[1] for v in entry)):
            raise ValueError(f"bad stream entry {entry!r}"[:200])
        b, m, seq, t = entry
        out[(b, m)] = (seq, t)
    return out

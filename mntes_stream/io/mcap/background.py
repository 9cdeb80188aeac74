"""A rotating MCAP recording written on a thread of its own (:class:`BackgroundMcapWriter`).

The caller (the recorder's receive loop) only reads each payload's header and
books it; framing, chunk compression and file writes run on the writer
thread, which zstd and lz4 (they release the GIL) and the disk share with the
caller's Python. Between the two is a bounded queue: when it is full the
caller waits (back-pressure, as the subscriber queue before it does), counted
in ``queue_full`` and ``wait_s``; nothing is dropped. The caller decides every
rotation, so the closing metadata it gives (the recorder's ledger) describes
exactly the messages handed over before it, which are those the closed file
holds.
"""

from __future__ import annotations

import collections
import contextlib
import threading
import time
from collections.abc import Callable, Mapping
from pathlib import Path

from mntes_stream.errors import ConfigError, TransportError
from mntes_stream.io.mcap.envelope import Envelope
from mntes_stream.io.mcap.rotating import RotatingMcapWriter

__all__ = ["BackgroundMcapWriter"]

_MSG, _JSON, _ROTATE, _CLOSE = range(4)
_BATCH = 256  # messages the writer takes per lock: the queue bound holds to within one batch
# The writer is woken once this many messages wait (or a command), else it looks every _LINGER_S: waking it for
# every message costs a thread switch each (and takes batches of one).
_WAKE = 32
_LINGER_S = 0.02


class BackgroundMcapWriter:
    """:class:`RotatingMcapWriter` on a writer thread, fed through a bounded queue.

    Parameters
    ----------
    directory, prefix, flush_interval_s, rotate_bytes, rotate_s, compression, chunk_size_bytes, fsync, metadata
        As :class:`RotatingMcapWriter`. Size rotation counts the file so far plus the payload still queued for it.
    queue_messages : int
        Messages handed over and not yet written, at most ...
    queue_bytes : int
        ... and payload bytes (one message always fits an empty queue).

    ``closing_metadata(file_seq)``, if set, gives the metadata records of the
    file ``file_seq`` (1-based in this run) as it is finished; it is called on
    the caller's thread, at the rotation (:meth:`rotate_if_full`, :meth:`tick`,
    :meth:`rotate`) or :meth:`close` it decides.
    A failed write (full disk) is raised once, by the next :meth:`write`,
    :meth:`tick` or :meth:`close`; later messages are counted in ``unwritten``.
    """

    def __init__(self, directory: str | Path, prefix: str = "mntes", *, flush_interval_s: float = 1.0,
                 rotate_bytes: int = 1 << 30, rotate_s: float = 3600.0, compression: str = "zstd",
                 chunk_size_bytes: int = 4 << 20, fsync: bool = False, metadata: Mapping | None = None,
                 queue_messages: int = 4096, queue_bytes: int = 64 << 20):
        if queue_messages < 1 or queue_bytes < 1:
            raise ConfigError(f"queue_messages and queue_bytes must be >= 1, got {queue_messages}, {queue_bytes}")
        # Validates every argument, opens the first file here (an unwritable directory fails the caller at once).
        self._w = RotatingMcapWriter(directory, prefix, flush_interval_s=flush_interval_s, rotate_bytes=0, rotate_s=0,
                                     compression=compression, chunk_size_bytes=chunk_size_bytes, fsync=fsync,
                                     metadata=metadata)
        if rotate_bytes < 0 or rotate_s < 0:
            raise ConfigError(f"rotate_bytes and rotate_s must be >= 0, got {rotate_bytes}, {rotate_s}")
        self.rotate_bytes = int(rotate_bytes)
        self.rotate_s = float(rotate_s)
        self.closing_metadata: Callable[[int], Mapping] | None = None
        self.queue_full = 0  # hand-overs that waited for room
        self.wait_s = 0.0  # time they waited
        self.queue_high_water = 0
        self._max_items = int(queue_messages)
        self._wake = min(_WAKE, self._max_items)
        self._max_bytes = int(queue_bytes)
        self._items: collections.deque = collections.deque()
        self._bytes = 0
        # A plain lock under the condition, taken as ``with self._lock`` (C, no Python frames): the caller takes
        # it for every message.
        self._lock = threading.Lock()
        self._cv = threading.Condition(self._lock)
        self._file_seq = 1
        self._file_queued = 0  # payload bytes handed over for the current file
        self._opened = time.monotonic()
        # (file_seq, file size so far, payload written into it): published by the writer thread, read by the caller
        self._progress = (1, self._w.size_bytes, 0)
        self.error: BaseException | None = None  # the writer thread's first failure
        self._raised = False
        self._closed = False
        self._thread = threading.Thread(target=self._run, name="mcap-writer", daemon=True)
        # Whether the writer thread still takes items: a flag it clears as it ends (Thread.is_alive, asked for every
        # message, cost as much as the rest of the hand-over).
        self._alive = True
        self._thread.start()

    # -- the caller's side
    def write(self, key: str, payload: bytes, log_time_ns: int, env: Envelope) -> None:
        """Hand one message over (its header read already); waits while the queue is full.

        Raises the writer's failure once (the message is still handed over: counted in ``unwritten``)."""
        n = len(payload)
        self._put((_MSG, key, payload, log_time_ns, env), n)
        self._file_queued += n
        self._raise_once()

    def rotate_if_full(self) -> None:
        """Rotate once the file so far plus what is queued for it reaches ``rotate_bytes``.

        Called by the caller after it has booked the messages it wrote, so the closing metadata counts them.
        """
        if self.rotate_bytes and not self._w.failed:
            seq, size, written = self._progress
            if (size + self._file_queued - written if seq == self._file_seq else self._file_queued) >= self.rotate_bytes:
                self.rotate()

    def write_json(self, topic: str, schema_name: str, schema: Mapping, message: Mapping, log_time_ns: int) -> None:
        """:meth:`RotatingMcapWriter.write_json`, in order with the messages."""
        self._put((_JSON, topic, schema_name, schema, message, log_time_ns), 0)

    def rotate(self) -> None:
        """Finish the current file after what was handed over so far, and start the next."""
        self._put((_ROTATE, self._closing()), 0)
        self._file_seq += 1
        self._file_queued = 0
        self._opened = time.monotonic()

    def tick(self) -> None:
        """Rotate if the file is full or old enough; raise the writer's failure (once). The writer flushes by
        itself."""
        self._raise_once()
        self.rotate_if_full()
        if self.rotate_s and time.monotonic() - self._opened >= self.rotate_s and not self._w.failed:
            self.rotate()

    def next_tick_s(self) -> float:
        """Seconds until :meth:`tick` has something to do (at most ``flush_interval_s``)."""
        due = self._opened + self.rotate_s - time.monotonic() if self.rotate_s else self._w.flush_interval_s
        return max(0.0, min(due, self._w.flush_interval_s))

    def close(self) -> None:
        """Write what is queued, finish the file (with its closing metadata) and stop the thread."""
        if self._closed:
            return
        self._closed = True
        if self._thread.is_alive():
            self._put((_CLOSE, self._closing()), 0, wait=False)
            self._thread.join()
        self._raise_once()

    def _closing(self) -> Mapping | None:
        return self.closing_metadata(self._file_seq) if self.closing_metadata is not None else None

    def _raise_once(self) -> None:
        if self.error is not None and not self._raised:
            self._raised = True
            raise self.error

    def _put(self, item, n: int, wait: bool = True) -> None:
        with self._lock:
            if not self._alive and item[0] != _CLOSE:
                self._w.unwritten += item[0] == _MSG  # the writer died (said by _raise_once): counted, not queued
                return
            if wait and self._items and (len(self._items) >= self._max_items or self._bytes + n > self._max_bytes):
                self.queue_full += 1
                self._cv.notify_all()  # the writer may be lingering for a batch that cannot grow
                t0 = time.monotonic()
                while (self._items and (len(self._items) >= self._max_items or self._bytes + n > self._max_bytes)
                       and self._alive):
                    self._cv.wait(0.1)
                self.wait_s += time.monotonic() - t0
            self._items.append(item)
            self._bytes += n
            queued = len(self._items)
            if queued > self.queue_high_water:
                self.queue_high_water = queued
            if queued == self._wake or item[0] != _MSG:
                self._cv.notify_all()

    # -- the writer thread
    def _run(self) -> None:
        try:
            self._write_items()
        finally:
            with self._lock:
                self._alive = False
                self._cv.notify_all()  # a caller waiting for room stops waiting

    def _write_items(self) -> None:
        w = self._w
        written = 0  # payload bytes written into the current file
        while True:
            with self._lock:
                if len(self._items) < self._wake:
                    self._cv.wait(_LINGER_S if self._items else max(w.next_tick_s(), 0.001))
                batch = [self._items.popleft() for _ in range(min(len(self._items), _BATCH))]
                for item in batch:
                    if item[0] == _MSG:
                        self._bytes -= len(item[2])
                self._cv.notify_all()  # room for a waiting caller
            for item in batch:
                try:
                    if item[0] == _MSG:
                        w.write(item[1], item[2], item[3], item[4])  # after a failure: counted in unwritten
                        written += len(item[2])
                    elif item[0] == _JSON:
                        w.write_json(*item[1:])
                    elif item[0] == _ROTATE:
                        if not w.failed:
                            self._progress = (self._progress[0], w.size_bytes, written)
                            w.rotate(item[1])
                            self._progress, written = (self._progress[0] + 1, w.size_bytes, 0), 0
                    else:
                        w.close(item[1])
                        return
                except BaseException as exc:  # a full disk, or anything else: said to the caller, never silent
                    self._fail(exc)
                    if item[0] == _CLOSE:
                        with contextlib.suppress(BaseException):
                            w.close()
                        return
            if batch and not w.failed:  # once per batch: the size asks the OS where the file is
                self._progress = (self._progress[0], w.size_bytes, written)
            try:
                w.tick()  # the flush cadence (the crash-loss bound)
            except BaseException as exc:
                self._fail(exc)

    def _fail(self, exc: BaseException) -> None:
        if self.error is None:
            self.error = exc if isinstance(exc, TransportError) else TransportError(
                f"MCAP writer thread failed: {type(exc).__name__}: {exc}")
        if not self._w.failed:  # not a write failure the writer counts itself: write nothing more, count the rest
            self._w.failed = str(self.error)

    # -- what the writer did (read from any thread)
    @property
    def messages(self) -> int:
        return self._w.messages

    @property
    def payload_bytes(self) -> int:
        return self._w.payload_bytes

    @property
    def invalid(self) -> int:
        return self._w.invalid

    @property
    def flushes(self) -> int:
        return self._w.flushes

    @property
    def unwritten(self) -> int:
        return self._w.unwritten

    @property
    def files(self) -> list[Path]:
        return list(self._w.files)

    @property
    def current_path(self) -> Path:
        return self._w.current_path

    def qsize(self) -> int:
        return len(self._items)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

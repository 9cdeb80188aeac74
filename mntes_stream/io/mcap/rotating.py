"""Recording into a rotating series of MCAP files (:class:`RotatingMcapWriter`)."""

from __future__ import annotations

import numbers
import re
import secrets
import time
from collections.abc import Mapping
from pathlib import Path

from mntes_stream.core.checks import finite_float
from mntes_stream.errors import ConfigError, TransportError
from mntes_stream.io import keys
from mntes_stream.io.mcap.envelope import RECORDING_METADATA, Envelope, peek_envelope, writer_description
from mntes_stream.io.mcap.recovery import killed_session
from mntes_stream.io.mcap.writer import McapFileWriter


class RotatingMcapWriter:
    """Record into ``<directory>/<prefix>-<seq>.mcap``, flushing on a cadence and rotating.

    Call :meth:`write` for every message and :meth:`tick` at least every
    ``flush_interval_s`` (also when no messages arrive): the loss window of a
    killed process is then at most ``flush_interval_s`` plus one tick period
    of received data.

    Parameters
    ----------
    directory : str or Path
        Created if missing.
    prefix : str
        File name prefix; sequence numbers continue after the highest existing one.
    flush_interval_s : float
        Longest time a received message stays only in memory.
    rotate_bytes : int
        Start a new file once the current one reaches this size (0: never).
    rotate_s : float
        Start a new file after this many seconds (0: never).
    compression, chunk_size_bytes, fsync
        As :class:`McapFileWriter`.
    metadata : mapping, optional
        Extra fields of the ``mntes.recording`` metadata (e.g. the recorder config).
    """

    def __init__(
        self,
        directory: str | Path,
        prefix: str = "mntes",
        *,
        flush_interval_s: float = 1.0,
        rotate_bytes: int = 1 << 30,
        rotate_s: float = 3600.0,
        compression: str = "zstd",
        chunk_size_bytes: int = 4 << 20,
        fsync: bool = False,
        metadata: Mapping[str, object] | None = None,
    ):
        if not isinstance(prefix, str) or not keys.NAME_PATTERN.fullmatch(prefix):
            raise ConfigError(f"prefix {prefix!r} must match [A-Za-z0-9_.-]+")
        flush_interval_s = finite_float("RotatingMcapWriter", "flush_interval_s", flush_interval_s)
        rotate_s = finite_float("RotatingMcapWriter", "rotate_s", rotate_s)
        if not flush_interval_s > 0:  # NaN would never flush: the crash-loss bound would be gone
            raise ConfigError(f"flush_interval_s must be > 0, got {flush_interval_s}")
        if not isinstance(rotate_bytes, numbers.Integral) or isinstance(rotate_bytes, bool) or rotate_bytes < 0 or rotate_s < 0:
            raise ConfigError(f"rotate_bytes (an integer) and rotate_s must be >= 0 (0 disables), got {rotate_bytes!r}, {rotate_s}")
        self.directory = Path(directory)
        try:
            self.directory.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise TransportError(f"cannot create recording directory {self.directory}: {exc}") from None
        self.prefix = prefix
        self.flush_interval_s = float(flush_interval_s)
        self.rotate_bytes = int(rotate_bytes)
        self.rotate_s = float(rotate_s)
        self._file_kw = dict(compression=compression, chunk_size_bytes=chunk_size_bytes, fsync=fsync)
        self._extra = dict(metadata or {})
        pattern = re.compile(re.escape(prefix) + r"-(\d+)\.mcap$")
        existing = [int(m.group(1)) for p in self.directory.iterdir() if (m := pattern.match(p.name))]
        self._seq = max(existing, default=0)
        # One id for every file of a recording session: readers keep two runs into one folder apart
        # (io/mcap/session.py). A recorder restarted after a crash (the newest file unfinished) continues it.
        self.session_id = (killed_session(self.directory / f"{prefix}-{self._seq:06d}.mcap") if existing else "") or \
            f"{time.strftime('%Y%m%dT%H%M%SZ', time.gmtime())}-{secrets.token_hex(3)}"
        self.files: list[Path] = []
        self.messages = 0
        self.messages_closed = 0  # messages in files finished (closed) so far
        self.unwritten = 0  # messages received that a failed write (full disk) may have left out
        self.failed = ""
        self.payload_bytes = 0
        self.invalid = 0
        self.flushes = 0
        self._current: McapFileWriter | None = None
        self._provenance: tuple[bytes, int] | None = None
        # Called as each file is finished (rotation, close): {name: {key: value}} metadata records to add then
        # (the recorder's ledger, mntes.ledger). None: nothing.
        self.closing_metadata = None
        self._open_next()

    @property
    def messages_flushed(self) -> int:
        """Messages certainly in the files: every finished file's, and the current one's up to its last flush."""
        return self.messages_closed + (self._current.messages_flushed if self._current is not None else 0)

    def _guard(self, call, *args):
        """Run a write; on failure say what the files hold, and count from then on only what is written."""
        try:
            return call(*args)
        except TransportError as exc:
            if self.failed:
                raise
            self.failed = str(exc)
            held = self.messages_flushed
            self.unwritten = self.messages - held
            self.messages = held  # the count every summary reports is now what the files hold
            names = ", ".join(p.name for p in self.files)
            raise TransportError(f"recording stopped: {exc}. In all: {held} messages in {len(self.files)} file(s) "
                                 f"({names}) up to their last flush, {self.unwritten} received after it may be "
                                 "missing") from None

    def _open_next(self, closing: Mapping | None = None) -> None:
        self._guard(self._rotate, closing)

    def rotate(self, closing: Mapping | None = None) -> None:
        """Finish the current file now (with the metadata records ``closing``, if given) and start the next."""
        self._open_next(closing)

    def _rotate(self, closing: Mapping | None = None) -> None:
        if self.failed:
            raise TransportError(f"recording stopped: {self.failed}")
        previous = self._current
        if previous is not None:
            self._provenance = previous.provenance
            try:
                self._close_file(previous, closing)
            finally:
                self.messages_closed += previous.messages_flushed
                self._current = None
        self._seq += 1
        path = self.directory / f"{self.prefix}-{self._seq:06d}.mcap"
        meta = writer_description(
            file_seq=str(self._seq),
            previous_file=self.files[-1].name if self.files else "",
            flush_interval_s=str(self.flush_interval_s),
            session=self.session_id,
            **self._extra,
        )
        self.files.append(path)  # before it opens: a disk too full to start it is said with its name
        self._current = McapFileWriter(path, metadata={RECORDING_METADATA: meta}, provenance=self._provenance, **self._file_kw)
        self._opened = time.monotonic()
        self._last_flush = self._opened

    def _close_file(self, file: McapFileWriter, closing: Mapping | None = None) -> None:
        """Finish one file: the closing metadata first (``closing``, else ``closing_metadata``), then summary and
        footer."""
        if closing is None and self.closing_metadata is not None:
            closing = self.closing_metadata(file.path)
        if closing and not file.failed:  # after a failed write: nothing more to write
            for name, data in closing.items():
                file.add_metadata(name, data)
        file.close()

    @property
    def current_path(self) -> Path:
        return self.files[-1]

    def write_json(self, topic: str, schema_name: str, schema: Mapping, message: Mapping, log_time_ns: int) -> None:
        """:meth:`McapFileWriter.write_json` on the current file (schemas and channels are per file)."""
        if self.failed:
            return
        self._guard(self._current.write_json, topic, schema_name, schema, message, log_time_ns)

    def write(self, key: str, payload: bytes, log_time_ns: int, env: Envelope | None = None) -> Envelope:
        """Store one message; the first failed write raises, later ones are only counted in ``unwritten``.

        Raising once lets the caller stop; not raising again lets it drain its queue and close its
        sessions in order (every message it hands over after the failure is counted, none written).
        ``env``: the payload's ``peek_envelope``, when the caller read it already.
        """
        if self.failed:
            self.unwritten += 1
            return peek_envelope(bytes(payload)) if env is None else env
        if self._current is None:
            raise TransportError("the writer is closed")
        self.messages += 1
        env = self._guard(self._current.write, key, payload, log_time_ns, env)
        self.payload_bytes += len(payload)
        self.invalid += bool(env.problem)
        if self.rotate_bytes and self._current.size_bytes >= self.rotate_bytes:
            self._open_next()
        return env

    def tick(self) -> None:
        """Flush if the cadence is due; rotate if the file is old enough."""
        if self._current is None or self.failed:
            return
        now = time.monotonic()
        if self.rotate_s and now - self._opened >= self.rotate_s:
            self._open_next()
        elif now - self._last_flush >= self.flush_interval_s:
            self.flush()

    def next_tick_s(self) -> float:
        """Seconds until :meth:`tick` has something to do."""
        return max(0.0, self._last_flush + self.flush_interval_s - time.monotonic())

    def flush(self) -> None:
        if self._current is None or self.failed:
            return
        self._guard(self._current.flush)
        self.flushes += 1
        self._last_flush = time.monotonic()

    @property
    def size_bytes(self) -> int:
        """The current file's size so far (its unflushed payload counted uncompressed); 0 once closed."""
        return self._current.size_bytes if self._current is not None else 0

    def close(self, closing: Mapping | None = None) -> None:
        """Finish the current file (with the metadata records ``closing``, if given); after a failed write, only
        close it (its messages up to the last flush stay)."""
        current = self._current
        if current is not None:
            try:
                self._guard(self._close_file, current, closing)
            finally:
                self.messages_closed += current.messages_flushed
                self._current = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()



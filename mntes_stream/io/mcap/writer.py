"""Writing recorded zenoh traffic to MCAP: one file (:class:`McapFileWriter`) or a rotating series."""

from __future__ import annotations

import contextlib
import json
import numbers
import os
import re
import time
from collections.abc import Mapping
from pathlib import Path

import msgpack
from mcap.writer import CompressionType, Writer

from mntes_stream import __version__
from mntes_stream.core.checks import finite_float
from mntes_stream.errors import ConfigError, SchemaError, TransportError
from mntes_stream.io import keys
from mntes_stream.io.describe import mcap_metadata
from mntes_stream.io.mcap.envelope import (
    MESSAGE_ENCODING,
    PROVENANCE_ATTACHMENT,
    PROVENANCE_SCHEMA,
    RECORDING_METADATA,
    SCHEMA_ENCODING,
    Envelope,
    as_metadata,
    check_provenance,
    peek_envelope,
    schema_text,
    writer_description,
)

_COMPRESSION = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}


class McapFileWriter:
    """Write recorded ``(key, payload, receive time)`` triples to one MCAP file.

    Parameters
    ----------
    path : str or Path
        The file to create (an existing file is an error: recordings are not overwritten).
    compression : {"zstd", "lz4", "none"}
    chunk_size_bytes : int
        Uncompressed size at which a chunk is closed (bigger compresses better).
    fsync : bool
        Also ``os.fsync`` on every :meth:`flush` (survives power loss, not only a
        killed process; costs a disk round trip per flush).
    metadata : mapping of str to mapping of str to str
        Metadata records written at the start (e.g. ``mntes.recording``).
    provenance : (bytes, int), optional
        The latest ``mntes.provenance`` payload and its receive time, repeated at
        the start of this file.
    """

    def __init__(
        self,
        path: str | Path,
        *,
        compression: str = "zstd",
        chunk_size_bytes: int = 4 << 20,
        fsync: bool = False,
        metadata: Mapping[str, Mapping[str, str]] | None = None,
        provenance: tuple[bytes, int] | None = None,
    ):
        if compression not in _COMPRESSION:
            raise ConfigError(f"compression must be one of {sorted(_COMPRESSION)}, got {compression!r}")
        if chunk_size_bytes < 1024:
            raise ConfigError(f"chunk_size_bytes must be >= 1024, got {chunk_size_bytes}")
        if provenance is not None:
            provenance = (bytes(provenance[0]), int(provenance[1]))
            env = check_provenance(provenance[0], peek_envelope(provenance[0]))
            if env.schema != PROVENANCE_SCHEMA or env.problem:
                raise SchemaError(f"provenance to repeat is not a valid {PROVENANCE_SCHEMA} message ({env.problem or env.schema!r})")
        self.path = Path(path)
        try:
            self._file = open(self.path, "xb")
        except OSError as exc:
            raise TransportError(f"cannot create {self.path}: {exc}") from None
        self._fsync = fsync
        self._schemas: dict[tuple[str, int], int] = {}
        self._json_schemas: dict[str, int] = {}
        self._json_channels: dict[str, int] = {}
        self._channels: dict[tuple[str, str, int, str], int] = {}
        self._provenance: tuple[bytes, int] | None = None
        self.messages = 0
        self.json_messages = 0
        self.payload_bytes = 0
        self.unflushed_bytes = 0
        self.invalid = 0
        self.closed = False
        try:
            self._writer = Writer(self._file, chunk_size=chunk_size_bytes, compression=_COMPRESSION[compression])
            self._writer.start(profile="", library=f"mntes-stream {__version__}")
            # Flag bits and units in every file: a reader needs no project code to know what bit 3 means.
            for name, data in {**mcap_metadata(), **(metadata or {})}.items():
                self._writer.add_metadata(name, {str(k): str(v) for k, v in data.items()})
            if provenance is not None:
                self._add_provenance(*provenance)
            self.flush()
        except BaseException as exc:
            # A writer that cannot start (disk full, ...) must not leak its handle;
            # closing flushes the same unwritable buffer again, which raises too.
            with contextlib.suppress(OSError):
                self._file.close()
            self.closed = True
            if isinstance(exc, OSError):
                raise TransportError(f"cannot write {self.path}: {exc}") from None
            raise

    # -- channels
    def _channel(self, topic: str, env: Envelope) -> int:
        problem = env.problem
        schema_id = 0
        if not problem:
            schema_id = self._schemas.get((env.schema, env.version), -1)
            if schema_id < 0:
                text = schema_text(env.schema, env.version)
                schema_id = 0 if text is None else self._writer.register_schema(env.schema, SCHEMA_ENCODING, text)
                self._schemas[(env.schema, env.version)] = schema_id
            if schema_id == 0:
                problem = "no JSON Schema for this name/version in this build"
        key = (topic, env.schema, env.version, problem)
        cid = self._channels.get(key)
        if cid is None:
            meta = {"mntes.schema": env.schema, "mntes.version": str(env.version)}
            if problem:
                meta["mntes.invalid"] = problem
            cid = self._writer.register_channel(topic, MESSAGE_ENCODING, schema_id, meta)
            self._channels[key] = cid
        return cid

    def write(self, key: str, payload: bytes, log_time_ns: int) -> Envelope:
        """Store one received message verbatim; returns what its envelope said."""
        payload = bytes(payload)
        env = check_provenance(payload, peek_envelope(payload))
        if env.problem:
            self.invalid += 1
        cid = self._channel(str(key), env)
        pub = env.publish_time_ns if env.publish_time_ns is not None and env.publish_time_ns >= 0 else log_time_ns
        seq = (env.seq or 0) & 0xFFFFFFFF
        self._writer.add_message(cid, log_time=int(log_time_ns), data=payload, publish_time=int(pub), sequence=seq)
        self.messages += 1
        self.payload_bytes += len(payload)
        self.unflushed_bytes += len(payload)
        if env.schema == PROVENANCE_SCHEMA and not env.problem and (self._provenance is None or payload != self._provenance[0]):
            self._add_provenance(payload, log_time_ns)
        return env

    def write_json(self, topic: str, schema_name: str, schema: Mapping, message: Mapping, log_time_ns: int) -> None:
        """One json message (encoding ``json``, its JSON Schema registered once as ``jsonschema``), e.g. the
        Foxglove channels of ``mntes_stream.foxglove.translate`` beside the msgpack originals."""
        sid = self._json_schemas.get(schema_name)
        if sid is None:
            sid = self._json_schemas[schema_name] = self._writer.register_schema(
                schema_name, SCHEMA_ENCODING, json.dumps(schema, separators=(",", ":")).encode())
        cid = self._json_channels.get(topic)
        if cid is None:
            cid = self._json_channels[topic] = self._writer.register_channel(topic, "json", sid,
                                                                             {"mntes.schema": schema_name})
        data = json.dumps(message, separators=(",", ":"), allow_nan=False).encode()
        self._writer.add_message(cid, log_time=int(log_time_ns), data=data, publish_time=int(log_time_ns))
        self.json_messages += 1
        self.unflushed_bytes += len(data)

    def add_attachment(self, name: str, media_type: str, data: bytes, log_time_ns: int, create_time_ns: int) -> None:
        self._writer.add_attachment(create_time=int(create_time_ns), log_time=int(log_time_ns), name=name,
                                    media_type=media_type, data=bytes(data))

    def _add_provenance(self, payload: bytes, log_time_ns: int) -> None:
        """Attachment + metadata for a provenance payload that :func:`check_provenance` accepted."""
        self._provenance = (payload, int(log_time_ns))
        env = peek_envelope(payload)
        self._writer.add_attachment(
            create_time=int(env.publish_time_ns or 0),
            log_time=int(log_time_ns),
            name=PROVENANCE_ATTACHMENT,
            media_type="application/msgpack",
            data=payload,
        )
        fields = msgpack.unpackb(payload, raw=False, strict_map_key=False)
        meta = as_metadata(fields)
        meta["recorded_log_time_ns"] = str(int(log_time_ns))
        self._writer.add_metadata(PROVENANCE_SCHEMA, meta)

    @property
    def provenance(self) -> tuple[bytes, int] | None:
        """The latest provenance payload written to this file and its receive time."""
        return self._provenance

    @property
    def size_bytes(self) -> int:
        """Bytes in the file so far plus the (uncompressed) payload not yet flushed."""
        return self._file.tell() + self.unflushed_bytes

    def add_metadata(self, name: str, data: Mapping[str, str]) -> None:
        self._writer.add_metadata(name, {str(k): str(v) for k, v in data.items()})

    def flush(self) -> None:
        """Close the open chunk and hand everything to the OS (and the disk if ``fsync``)."""
        self._writer.flush()
        if self._fsync:
            os.fsync(self._file.fileno())
        self.unflushed_bytes = 0

    def close(self) -> None:
        """Finish the file (summary, indexes, footer) and close it."""
        if self.closed:
            return
        self.closed = True
        try:
            self._writer.finish()
            self._file.flush()
            if self._fsync:
                os.fsync(self._file.fileno())
        finally:
            self._file.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


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
        self.files: list[Path] = []
        self.messages = 0
        self.payload_bytes = 0
        self.invalid = 0
        self.flushes = 0
        self._current: McapFileWriter | None = None
        self._provenance: tuple[bytes, int] | None = None
        self._open_next()

    def _open_next(self) -> None:
        previous = self._current
        if previous is not None:
            self._provenance = previous.provenance
            previous.close()
        self._seq += 1
        path = self.directory / f"{self.prefix}-{self._seq:06d}.mcap"
        meta = writer_description(
            file_seq=str(self._seq),
            previous_file=self.files[-1].name if self.files else "",
            flush_interval_s=str(self.flush_interval_s),
            **self._extra,
        )
        self._current = McapFileWriter(path, metadata={RECORDING_METADATA: meta}, provenance=self._provenance, **self._file_kw)
        self.files.append(path)
        self._opened = time.monotonic()
        self._last_flush = self._opened

    @property
    def current_path(self) -> Path:
        return self._current.path

    def write_json(self, topic: str, schema_name: str, schema: Mapping, message: Mapping, log_time_ns: int) -> None:
        """:meth:`McapFileWriter.write_json` on the current file (schemas and channels are per file)."""
        self._current.write_json(topic, schema_name, schema, message, log_time_ns)

    def write(self, key: str, payload: bytes, log_time_ns: int) -> Envelope:
        env = self._current.write(key, payload, log_time_ns)
        self.messages += 1
        self.payload_bytes += len(payload)
        self.invalid += bool(env.problem)
        if self.rotate_bytes and self._current.size_bytes >= self.rotate_bytes:
            self._open_next()
        return env

    def tick(self) -> None:
        """Flush if the cadence is due; rotate if the file is old enough."""
        now = time.monotonic()
        if self.rotate_s and now - self._opened >= self.rotate_s:
            self._open_next()
        elif now - self._last_flush >= self.flush_interval_s:
            self.flush()

    def next_tick_s(self) -> float:
        """Seconds until :meth:`tick` has something to do."""
        return max(0.0, self._last_flush + self.flush_interval_s - time.monotonic())

    def flush(self) -> None:
        self._current.flush()
        self.flushes += 1
        self._last_flush = time.monotonic()

    def close(self) -> None:
        if self._current is not None:
            self._current.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


# ----------------------------------------------------------------------------- reader


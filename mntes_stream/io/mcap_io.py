"""MCAP files of recorded zenoh traffic: writer (with rotation) and a recovering reader.

File layout (one file = a self-describing piece of a session)
-------------------------------------------------------------
- One channel per zenoh key (topic = key), message encoding ``msgpack``; the
  payload bytes are stored verbatim. The channel's schema is the JSON Schema
  text (encoding ``jsonschema``) of the payload's ``schema``/``version``, so the
  file explains itself. A key that carries a message this build has no schema
  for, or bytes that are not an mntes envelope, gets an extra schema-less
  channel on the same topic (channel metadata ``mntes.schema`` names what the
  payload claimed, ``mntes.invalid`` says why it has no schema): nothing is
  dropped, and nothing is mislabelled. An envelope that claims
  ``mntes.provenance`` but does not decode as one is such an invalid payload.
- ``log_time`` is the receive time (ns since epoch); ``publish_time`` the
  message's own ``t_pub_ns`` (else ``t_ns``, else the receive time);
  ``sequence`` the message's ``seq`` modulo 2**32 (else 0).
- Every valid ``mntes.provenance`` message whose bytes differ from the previous
  one is also stored as an attachment ``mntes.provenance.msgpack`` (verbatim) and a
  metadata record ``mntes.provenance`` (its fields as strings); each file
  repeats the latest provenance at its start, so one file alone reproduces its
  conversion. The writer's own description (software version, host, config)
  is the metadata record ``mntes.recording``.
- Chunked and compressed (zstd by default).

Crash safety
------------
:class:`McapFileWriter` only ever leaves complete chunks behind when its
:meth:`~McapFileWriter.flush` has run: a process killed between flushes loses
the messages since the last flush (and the summary at the end of the file).
:class:`RotatingMcapWriter` flushes every ``flush_interval_s`` and rotates by
size or duration. The reader recovers every complete chunk of a file whose
writer died (:class:`TruncatedFileWarning`, ``FileInfo.complete == False``) and
reads a directory or a list of rotated files as one time-ordered session.
"""

from __future__ import annotations

import heapq
import io
import json
import numbers
import os
import re
import socket
import struct
import time
import warnings
import zlib
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path

import msgpack
from mcap.data_stream import ReadDataStream
from mcap.opcode import Opcode
from mcap.records import Attachment, Channel, Chunk, Message, Metadata, Schema
from mcap.writer import CompressionType, Writer

from mntes_stream import __version__
from mntes_stream.core.checks import finite_float
from mntes_stream.errors import ConfigError, SchemaError, TransportError
from mntes_stream.io import keys

__all__ = [
    "MESSAGE_ENCODING",
    "PROVENANCE_ATTACHMENT",
    "FileInfo",
    "McapFileWriter",
    "RecordedAttachment",
    "RecordedMessage",
    "RecordedMetadata",
    "RotatingMcapWriter",
    "Session",
    "TruncatedFileWarning",
    "iter_messages",
    "latest_provenance",
    "peek_envelope",
    "read_attachments",
    "read_metadata",
    "session_files",
    "topic_matcher",
]

MESSAGE_ENCODING = "msgpack"
SCHEMA_ENCODING = "jsonschema"
PROVENANCE_SCHEMA = "mntes.provenance"
PROVENANCE_ATTACHMENT = "mntes.provenance.msgpack"
RECORDING_METADATA = "mntes.recording"
_MAGIC = b"\x89MCAP0\r\n"
_COMPRESSION = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}
_RECORD_HEADER = struct.Struct("<BQ")


class TruncatedFileWarning(UserWarning):
    """A file was not finished by its writer; its complete chunks were recovered."""


# ----------------------------------------------------------------------------- envelope


@dataclass(frozen=True, slots=True)
class Envelope:
    """What the recorder needs to know about a payload without trusting it."""

    schema: str  # "" if the payload is not an mntes envelope
    version: int  # 0 if unknown
    publish_time_ns: int | None
    seq: int | None
    problem: str  # "" if the envelope is well formed


def peek_envelope(payload: bytes) -> Envelope:
    """Read ``schema``, ``version``, ``t_pub_ns``/``t_ns`` and ``seq``; never raises."""
    try:
        msg = msgpack.unpackb(payload, raw=False, strict_map_key=False)
    except Exception as exc:  # msgpack raises several unrelated types
        return Envelope("", 0, None, None, f"malformed msgpack ({type(exc).__name__})")
    if not isinstance(msg, dict):
        return Envelope("", 0, None, None, f"payload is a {type(msg).__name__}, not a map")
    name, version = msg.get("schema"), msg.get("version")
    if not isinstance(name, str) or not isinstance(version, int) or isinstance(version, bool):
        return Envelope("", 0, None, None, "no string 'schema' and integer 'version'")
    t_pub = next((msg[k] for k in ("t_pub_ns", "t_ns") if _is_int(msg.get(k))), None)
    seq = msg.get("seq") if _is_int(msg.get("seq")) else None
    return Envelope(name, version, t_pub, seq, "")


def _is_int(v) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _schema_text(name: str, version: int) -> bytes | None:
    from mntes_stream.io.codec import json_schema

    try:
        return json.dumps(json_schema(name, version), indent=1).encode()
    except SchemaError:
        return None


def _as_metadata(fields: Mapping) -> dict[str, str]:
    """Flatten a decoded message to MCAP metadata (str -> str); bytes are summarised. Never raises."""
    out = {}
    for k, v in fields.items():
        if isinstance(v, str):
            out[str(k)] = v
        elif isinstance(v, (bytes, bytearray)):
            out[str(k)] = f"<{len(v)} bytes: see attachment {PROVENANCE_ATTACHMENT}>"
        else:
            try:
                out[str(k)] = json.dumps(v, default=repr, sort_keys=True)
            except (TypeError, ValueError):  # e.g. bytes or mixed-type map keys
                out[str(k)] = repr(v)
    return out


def _check_provenance(payload: bytes, env: Envelope) -> Envelope:
    """``env``, or ``env`` with a problem if a ``mntes.provenance`` envelope does not decode as one.

    Only a valid provenance becomes an attachment and a metadata record; any
    peer on the setup's keys can publish, so nothing here may raise.
    """
    if env.problem or env.schema != PROVENANCE_SCHEMA:
        return env
    from mntes_stream.io.messages import Provenance

    try:
        Provenance.from_bytes(payload)
    except Exception as exc:  # SchemaError normally; anything else must not stop a recorder either
        # A bounded set of problem strings: each distinct one is a channel.
        reason = getattr(exc, "reason", "") or type(exc).__name__
        return Envelope(env.schema, env.version, env.publish_time_ns, env.seq, f"invalid {PROVENANCE_SCHEMA} message ({reason})")
    return env


def writer_description(**extra) -> dict[str, str]:
    """The ``mntes.recording`` metadata: who wrote the file, where, when."""
    import mcap

    desc = {
        "software": f"mntes-stream {__version__}",
        "mcap_library": f"mcap-python {getattr(mcap, '__version__', '?')}",
        "host": socket.gethostname(),
        "created_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
    }
    desc.update({k: v if isinstance(v, str) else json.dumps(v, default=str) for k, v in extra.items()})
    return desc


# ----------------------------------------------------------------------------- writer


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
            env = _check_provenance(provenance[0], peek_envelope(provenance[0]))
            if env.schema != PROVENANCE_SCHEMA or env.problem:
                raise SchemaError(f"provenance to repeat is not a valid {PROVENANCE_SCHEMA} message ({env.problem or env.schema!r})")
        self.path = Path(path)
        try:
            self._file = open(self.path, "xb")
        except OSError as exc:
            raise TransportError(f"cannot create {self.path}: {exc}") from None
        self._fsync = fsync
        self._writer = Writer(self._file, chunk_size=chunk_size_bytes, compression=_COMPRESSION[compression])
        self._writer.start(profile="", library=f"mntes-stream {__version__}")
        self._schemas: dict[tuple[str, int], int] = {}
        self._channels: dict[tuple[str, str, int, str], int] = {}
        self._provenance: tuple[bytes, int] | None = None
        self.messages = 0
        self.payload_bytes = 0
        self.unflushed_bytes = 0
        self.invalid = 0
        self.closed = False
        for name, data in (metadata or {}).items():
            self._writer.add_metadata(name, dict(data))
        if provenance is not None:
            self._add_provenance(*provenance)
        self.flush()

    # -- channels
    def _channel(self, topic: str, env: Envelope) -> int:
        problem = env.problem
        schema_id = 0
        if not problem:
            schema_id = self._schemas.get((env.schema, env.version), -1)
            if schema_id < 0:
                text = _schema_text(env.schema, env.version)
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
        env = _check_provenance(payload, peek_envelope(payload))
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

    def _add_provenance(self, payload: bytes, log_time_ns: int) -> None:
        """Attachment + metadata for a provenance payload that :func:`_check_provenance` accepted."""
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
        meta = _as_metadata(fields)
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


@dataclass(frozen=True, slots=True)
class RecordedMessage:
    """One recorded message; ``payload`` is exactly the bytes received."""

    topic: str
    schema_name: str  # "" when the payload was not an mntes envelope
    log_time_ns: int
    publish_time_ns: int
    payload: bytes
    schema_version: int = 0
    sequence: int = 0


@dataclass(frozen=True, slots=True)
class RecordedMetadata:
    name: str
    data: dict
    path: str


@dataclass(frozen=True, slots=True)
class RecordedAttachment:
    name: str
    media_type: str
    log_time_ns: int
    create_time_ns: int
    data: bytes
    path: str


@dataclass(frozen=True, slots=True)
class FileInfo:
    """What a file holds and whether it was finished by its writer.

    ``complete`` is False for a file whose writer died: ``problem`` says where
    reading stopped and ``recovered_bytes`` how much of ``size_bytes`` was
    usable (everything up to the last complete record).
    """

    path: str
    complete: bool
    problem: str
    size_bytes: int
    recovered_bytes: int
    chunks: int
    messages: int
    start_ns: int | None
    end_ns: int | None


@dataclass(slots=True)
class _ChunkRef:
    start_ns: int
    end_ns: int
    offset: int
    length: int


@dataclass(slots=True)
class _ChannelInfo:
    topic: str
    schema_name: str
    schema_version: int


@dataclass
class _FileIndex:
    path: Path
    size: int
    complete: bool = False
    problem: str = ""
    recovered: int = 0
    chunks: list[_ChunkRef] = field(default_factory=list)
    schemas: dict[int, Schema] = field(default_factory=dict)
    channels: dict[int, _ChannelInfo] = field(default_factory=dict)
    loose: list[Message] = field(default_factory=list)
    attachments: list[tuple[int, int]] = field(default_factory=list)
    metadata: list[tuple[int, int]] = field(default_factory=list)
    counts: dict[int, int] = field(default_factory=dict)

    def add_channel(self, ch: Channel) -> None:
        meta = ch.metadata or {}
        schema = self.schemas.get(ch.schema_id)
        name = schema.name if schema is not None else meta.get("mntes.schema", "")
        try:
            version = int(meta.get("mntes.version", "0"))
        except ValueError:
            version = 0
        self.channels[ch.id] = _ChannelInfo(ch.topic, name, version)

    def info(self) -> FileInfo:
        msgs = sum(self.counts.values())
        starts = [c.start_ns for c in self.chunks] + [m.log_time for m in self.loose]
        ends = [c.end_ns for c in self.chunks] + [m.log_time for m in self.loose]
        return FileInfo(
            str(self.path), self.complete, self.problem, self.size, self.recovered,
            len(self.chunks), msgs, min(starts, default=None), max(ends, default=None),
        )


def _chunk_records(chunk: Chunk, messages: bool = True) -> Iterator[Schema | Channel | Message]:
    """Decompress one chunk (checking its CRC) and yield its records."""
    if chunk.compression == "zstd":
        import zstandard

        data = zstandard.ZstdDecompressor().decompress(chunk.data, max_output_size=chunk.uncompressed_size)
    elif chunk.compression == "lz4":
        import lz4.frame

        data = lz4.frame.decompress(chunk.data)
    elif chunk.compression == "":
        data = chunk.data
    else:
        raise TransportError(f"unsupported chunk compression {chunk.compression!r}")
    if len(data) != chunk.uncompressed_size:
        raise TransportError("chunk size does not match its header")
    if chunk.uncompressed_crc and zlib.crc32(data) != chunk.uncompressed_crc:
        raise TransportError("chunk CRC mismatch")
    pos, n = 0, len(data)
    view = memoryview(data)
    while pos < n:
        if pos + 9 > n:
            raise TransportError("chunk ends inside a record header")
        opcode, length = _RECORD_HEADER.unpack_from(data, pos)
        body_start, pos = pos + 9, pos + 9 + length
        if pos > n:
            raise TransportError("chunk record overruns the chunk")
        if opcode == Opcode.MESSAGE:
            if messages:
                yield Message.read(ReadDataStream(io.BytesIO(view[body_start:pos])), length)
        elif opcode == Opcode.CHANNEL:
            yield Channel.read(ReadDataStream(io.BytesIO(view[body_start:pos])))
        elif opcode == Opcode.SCHEMA:
            yield Schema.read(ReadDataStream(io.BytesIO(view[body_start:pos])))


def _read_record(f, offset: int, length: int, expect: int) -> ReadDataStream:
    f.seek(offset)
    raw = f.read(length)
    if len(raw) != length or raw[0] != expect:
        raise TransportError(f"record at offset {offset} is not opcode {expect:#x}")
    return ReadDataStream(io.BytesIO(raw[9:]))


def _index_from_summary(idx: _FileIndex, f) -> bool:
    """Use the summary section of a finished file; False if there is none usable."""
    from mcap.reader import SeekingReader

    try:
        f.seek(0)
        summary = SeekingReader(f).get_summary()
    except Exception:  # a file without a valid footer: the writer died
        return False
    if summary is None or summary.statistics is None:
        return False
    stats = summary.statistics
    if stats.message_count and not summary.chunk_indexes:
        return False  # unchunked messages: only a linear scan finds them
    if any(cid not in summary.channels for cid in stats.channel_message_counts):
        return False
    idx.schemas.update(summary.schemas)
    for ch in summary.channels.values():
        idx.add_channel(ch)
    idx.chunks = [
        _ChunkRef(ci.message_start_time, ci.message_end_time, ci.chunk_start_offset, ci.chunk_length)
        for ci in summary.chunk_indexes
    ]
    idx.counts = dict(stats.channel_message_counts)
    idx.attachments = [(a.offset, a.length) for a in summary.attachment_indexes]
    idx.metadata = [(m.offset, m.length) for m in summary.metadata_indexes]
    idx.complete = True
    idx.recovered = idx.size
    return True


def _index_by_scan(idx: _FileIndex, f) -> None:
    """Walk the records of a file whose end is missing, keeping every complete one."""
    pos = len(_MAGIC)
    size = idx.size
    f.seek(pos)
    while True:
        hdr = f.read(9)
        if len(hdr) < 9:
            idx.problem = "file ends without a footer" if not hdr else f"file ends inside a record header at byte {pos}"
            break
        opcode, length = _RECORD_HEADER.unpack(hdr)
        end = pos + 9 + length
        if end > size:
            idx.problem = f"file ends inside a record (opcode {opcode:#x}) at byte {pos}"
            break
        if opcode == Opcode.CHUNK:
            body = f.read(length)
            try:
                chunk = Chunk.read(ReadDataStream(io.BytesIO(body)))
                counted = 0
                for rec in _chunk_records(chunk):
                    if isinstance(rec, Schema):
                        idx.schemas[rec.id] = rec
                    elif isinstance(rec, Channel):
                        idx.add_channel(rec)
                    else:
                        idx.counts[rec.channel_id] = idx.counts.get(rec.channel_id, 0) + 1
                        counted += 1
                if counted:
                    idx.chunks.append(_ChunkRef(chunk.message_start_time, chunk.message_end_time, pos, 9 + length))
            except Exception as exc:  # a damaged chunk: skip it, keep going
                idx.problem = f"damaged chunk at byte {pos} skipped ({exc})"
        elif opcode in (Opcode.SCHEMA, Opcode.CHANNEL, Opcode.MESSAGE):
            # Records outside chunks (other writers): no CRC, so a damaged one means the
            # framing after it cannot be trusted either. Keep what came before, stop.
            try:
                stream = ReadDataStream(io.BytesIO(f.read(length)))
                if opcode == Opcode.SCHEMA:
                    rec = Schema.read(stream)
                elif opcode == Opcode.CHANNEL:
                    rec = Channel.read(stream)
                else:
                    rec = Message.read(stream, length)
            except Exception as exc:  # mcap raises EndOfFile, struct.error, UnicodeDecodeError...
                idx.problem = f"damaged record (opcode {opcode:#x}) at byte {pos} ({type(exc).__name__}: {exc}); stopped there"
                break
            if opcode == Opcode.SCHEMA:
                idx.schemas[rec.id] = rec
            elif opcode == Opcode.CHANNEL:
                idx.add_channel(rec)
            else:
                idx.loose.append(rec)
                idx.counts[rec.channel_id] = idx.counts.get(rec.channel_id, 0) + 1
        elif opcode == Opcode.ATTACHMENT:
            idx.attachments.append((pos, 9 + length))
        elif opcode == Opcode.METADATA:
            idx.metadata.append((pos, 9 + length))
        elif opcode == Opcode.FOOTER:
            pos = end
            f.seek(pos)
            idx.complete = f.read(len(_MAGIC)) == _MAGIC
            if not idx.complete:
                idx.problem = "footer not followed by the closing magic"
            idx.recovered = pos + (len(_MAGIC) if idx.complete else 0)
            return
        pos = end
        f.seek(pos)
        idx.recovered = pos


def _index_file(path: Path) -> _FileIndex:
    try:
        size = path.stat().st_size
        f = open(path, "rb")
    except OSError as exc:
        raise TransportError(f"cannot read {path}: {exc}") from None
    idx = _FileIndex(path=path, size=size)
    with f:
        head = f.read(len(_MAGIC))
        if head != _MAGIC[: len(head)]:
            raise TransportError(f"{path} is not an MCAP file (bad magic)")
        if len(head) < len(_MAGIC):
            idx.problem = "file shorter than the MCAP magic"
            return idx
        if not _index_from_summary(idx, f):
            _index_by_scan(idx, f)
    return idx


def session_files(source: str | Path | Iterable[str | Path]) -> list[Path]:
    """The files of a session: a file, a directory (its ``*.mcap``, by name), or a list."""
    if isinstance(source, (str, Path)):
        p = Path(source)
        if p.is_dir():
            files = sorted(p.glob("*.mcap"))
            if not files:
                raise TransportError(f"no .mcap files in {p}")
            return files
        if not p.exists():
            raise TransportError(f"no such file: {p}")
        return [p]
    files = [f for s in source for f in session_files(s)]
    if not files:
        raise TransportError("no MCAP files given")
    return files


def _glob_regex(expr: str) -> re.Pattern:
    """zenoh key-expression wildcards: ``*`` one chunk, ``**`` any number of chunks."""
    toks = expr.split("/")
    if toks == ["**"]:
        return re.compile(r".+$")
    rx = ""
    for i, tok in enumerate(toks):
        if tok == "**":
            rx += "(?:[^/]+/)*" if i == 0 else "(?:/[^/]+)*"
            continue
        pat = "[^/]+" if tok == "*" else re.escape(tok).replace(r"\*", "[^/]*")
        rx += pat if i == 0 or (i == 1 and toks[0] == "**") else "/" + pat
    return re.compile(rx + "$")


def topic_matcher(topics: str | Iterable[str] | None):
    """A predicate on topics: exact names, or zenoh-style ``*`` / ``**`` patterns."""
    if topics is None:
        return lambda t: True
    topics = [topics] if isinstance(topics, str) else list(topics)
    exact = {t for t in topics if "*" not in t}
    patterns = [_glob_regex(t) for t in topics if "*" in t]
    return lambda t: t in exact or any(p.match(t) for p in patterns)


class Session:
    """One recorded session: a file, a directory, or several (rotated) files.

    Indexing happens at construction: a finished file is indexed from its
    summary; an unfinished one by walking its records (every complete chunk
    is kept; see :attr:`files` for what was recovered). A file that is not
    MCAP at all raises :class:`TransportError`.

    Parameters
    ----------
    source : path, directory, or iterable of paths
    warn : bool
        Emit a :class:`TruncatedFileWarning` per unfinished file.
    """

    def __init__(self, source, *, warn: bool = True):
        self._index = [_index_file(p) for p in session_files(source)]
        self.files = [ix.info() for ix in self._index]
        if warn:
            for fi in self.files:
                if not fi.complete:
                    warnings.warn(
                        f"{fi.path}: not finished by its writer ({fi.problem}); recovered "
                        f"{fi.messages} messages in {fi.chunks} complete chunks, "
                        f"{fi.recovered_bytes} of {fi.size_bytes} bytes",
                        TruncatedFileWarning,
                        stacklevel=3,
                    )
                elif fi.problem:
                    warnings.warn(f"{fi.path}: {fi.problem}", TruncatedFileWarning, stacklevel=3)

    @property
    def complete(self) -> bool:
        """True when every file was finished by its writer."""
        return all(fi.complete for fi in self.files)

    def message_counts(self) -> dict[str, int]:
        """Messages per topic (recoverable ones, for unfinished files)."""
        out: dict[str, int] = {}
        for ix in self._index:
            for cid, n in ix.counts.items():
                ch = ix.channels.get(cid)
                if ch is not None:
                    out[ch.topic] = out.get(ch.topic, 0) + n
        return out

    def count(self, topics=None) -> int:
        match = topic_matcher(topics)
        return sum(n for t, n in self.message_counts().items() if match(t))

    @property
    def start_ns(self) -> int | None:
        return min((fi.start_ns for fi in self.files if fi.start_ns is not None), default=None)

    @property
    def end_ns(self) -> int | None:
        return max((fi.end_ns for fi in self.files if fi.end_ns is not None), default=None)

    def iter_messages(self, topics=None, start_ns: int | None = None, end_ns: int | None = None) -> Iterator[RecordedMessage]:
        """Messages in log-time order (ties keep file order), ``start_ns <= t < end_ns``.

        Parameters
        ----------
        topics : str or iterable of str, optional
            Exact topics or zenoh-style patterns (``mntes/lab/counts/**``).
        """
        match = topic_matcher(topics)
        lo = -1 if start_ns is None else int(start_ns)
        hi = 1 << 64 if end_ns is None else int(end_ns)
        refs = []  # (start, file, order, chunk ref or loose messages)
        for fi, ix in enumerate(self._index):
            wanted = {cid for cid, ch in ix.channels.items() if match(ch.topic)}
            if not wanted:
                continue
            for k, c in enumerate(ix.chunks):
                if c.end_ns >= lo and c.start_ns < hi:
                    refs.append((c.start_ns, fi, k, c))
            if ix.loose:
                refs.append((min(m.log_time for m in ix.loose), fi, len(ix.chunks), ix.loose))
        refs.sort(key=lambda r: r[:3])
        handles: dict[int, object] = {}
        heap: list = []
        i = orphans = 0
        try:
            while i < len(refs) or heap:
                # Load every chunk that may hold a message older than the heap's head.
                while i < len(refs) and (not heap or refs[i][0] <= heap[0][0]):
                    _, fi, k, ref = refs[i]
                    i += 1
                    ix = self._index[fi]
                    for j, msg in enumerate(self._load(ix, fi, ref, handles)):
                        ch = ix.channels.get(msg.channel_id)
                        if ch is None:  # its channel record was in a damaged chunk
                            orphans += 1
                            continue
                        if not match(ch.topic) or not lo <= msg.log_time < hi:
                            continue
                        heapq.heappush(heap, (msg.log_time, fi, k, j, ch, msg))
                if heap:
                    t, _, _, _, ch, msg = heapq.heappop(heap)
                    yield RecordedMessage(
                        ch.topic, ch.schema_name, t, msg.publish_time, bytes(msg.data), ch.schema_version, msg.sequence
                    )
        finally:
            for h in handles.values():
                h.close()
        if orphans:
            warnings.warn(f"{orphans} messages skipped: their channel was defined in a damaged chunk",
                          TruncatedFileWarning, stacklevel=2)

    def _load(self, ix: _FileIndex, fi: int, ref, handles) -> list[Message]:
        if isinstance(ref, list):
            return ref
        f = handles.get(fi)
        if f is None:
            f = handles[fi] = open(ix.path, "rb")
        try:
            chunk = Chunk.read(_read_record(f, ref.offset, ref.length, Opcode.CHUNK))
            out = []
            for rec in _chunk_records(chunk):
                if isinstance(rec, Message):
                    out.append(rec)
                elif isinstance(rec, Schema):
                    ix.schemas.setdefault(rec.id, rec)
                elif rec.id not in ix.channels:
                    ix.add_channel(rec)
            return out
        except Exception as exc:
            warnings.warn(f"{ix.path}: damaged chunk at byte {ref.offset} skipped ({exc})", TruncatedFileWarning, stacklevel=4)
            return []

    def _records(self, which: str, opcode: int, read) -> Iterator:
        """``read(stream, path)`` of every indexed record of one kind; a damaged one is skipped with a warning."""
        for ix in self._index:
            try:
                f = open(ix.path, "rb")
            except OSError as exc:
                raise TransportError(f"cannot read {ix.path}: {exc}") from None
            with f:
                for off, length in getattr(ix, which):
                    try:
                        rec = read(_read_record(f, off, length, opcode), str(ix.path))
                    except Exception as exc:  # no CRC on these records: a damaged one is unreadable
                        warnings.warn(f"{ix.path}: damaged record (opcode {opcode:#x}) at byte {off} skipped ({exc})",
                                      TruncatedFileWarning, stacklevel=4)
                        continue
                    yield rec

    def metadata(self) -> list[RecordedMetadata]:
        """Every metadata record, in file order (a name may repeat, e.g. provenance changes)."""
        def read(stream, path):
            m = Metadata.read(stream)
            return RecordedMetadata(m.name, dict(m.metadata), path)

        return list(self._records("metadata", Opcode.METADATA, read))

    def attachments(self) -> list[RecordedAttachment]:
        """Every attachment, in file order."""
        def read(stream, path):
            a = Attachment.read(stream)
            return RecordedAttachment(a.name, a.media_type, a.log_time, a.create_time, bytes(a.data), path)

        return list(self._records("attachments", Opcode.ATTACHMENT, read))


def iter_messages(source, topics=None, start_ns: int | None = None, end_ns: int | None = None) -> Iterator[RecordedMessage]:
    """Recorded messages of a file, directory or list of files, in log-time order.

    Unfinished files (writer killed) are recovered up to their last complete
    chunk with a :class:`TruncatedFileWarning`; a file that is not MCAP raises
    :class:`TransportError`. See :meth:`Session.iter_messages`.
    """
    return Session(source).iter_messages(topics, start_ns, end_ns)


def read_metadata(source) -> list[RecordedMetadata]:
    """Metadata records of a file, directory or list of files (file order)."""
    return Session(source, warn=False).metadata()


def read_attachments(source) -> list[RecordedAttachment]:
    """Attachments of a file, directory or list of files (file order)."""
    return Session(source, warn=False).attachments()


def latest_provenance(source) -> bytes | None:
    """The most recent ``mntes.provenance`` payload stored in the session, or None."""
    found = [(a.log_time_ns, k, a.data) for k, a in enumerate(read_attachments(source)) if a.name == PROVENANCE_ATTACHMENT]
    return max(found)[2] if found else None

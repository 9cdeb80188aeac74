"""Writing recorded zenoh traffic to one MCAP file (:class:`McapFileWriter`); a rotating series: :mod:`.rotating`."""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
import struct
from collections.abc import Mapping
from pathlib import Path

import msgpack
from mcap.data_stream import RecordBuilder
from mcap.opcode import Opcode
from mcap.records import ChunkIndex
from mcap.writer import CompressionType, IndexType, Writer
from zlib_ng.zlib_ng import crc32  # zlib's CRC, 9x faster (pyproject.toml)

from mntes_stream import __version__
from mntes_stream.errors import ConfigError, SchemaError, TransportError
from mntes_stream.io.describe import mcap_metadata
from mntes_stream.io.mcap.envelope import (
    MESSAGE_ENCODING,
    PROVENANCE_ATTACHMENT,
    PROVENANCE_SCHEMA,
    SCHEMA_ENCODING,
    Envelope,
    as_metadata,
    check_provenance,
    peek_envelope,
    schema_text,
)

_COMPRESSION = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}
_MESSAGE_HEAD = struct.Struct("<BQHIQQ").pack  # opcode, record length, channel, sequence, log time, publish time
_CHUNK_HEAD = struct.Struct("<BQQQQI").pack  # opcode, record length, start, end, uncompressed size and crc


class _Chunk:
    """The open chunk of a :class:`_LeanWriter`: its records as a list of bytes, joined once when it closes.

    Stands in for ``mcap``'s ``ChunkBuilder`` (same attributes and methods, which the library's ``Writer``
    calls for channels and schemas), where every message went through a ``Message`` object and a
    ``BytesIO`` (a copy of the payload, and a seek and rewrite of each record's length).
    """

    def __init__(self) -> None:
        self.parts: list = []
        self.count = 0  # bytes of records so far
        self.num_messages = 0
        self.message_start_time = self.message_end_time = 0
        # channel id -> [log time, offset, log time, offset, ...]: the chunk's message index records, flat
        self.message_indices: dict[int, list] = {}

    def add_message_bytes(self, channel_id: int, sequence: int, log_time: int, publish_time: int, data: bytes) -> None:
        """One message record (as ``mcap.records.Message.write`` lays it out) and its index entry."""
        if self.num_messages == 0:
            self.message_start_time = self.message_end_time = log_time
        elif log_time < self.message_start_time:
            self.message_start_time = log_time
        elif log_time > self.message_end_time:
            self.message_end_time = log_time
        index = self.message_indices.get(channel_id)
        if index is None:
            index = self.message_indices[channel_id] = []
        index += (log_time, self.count)
        self.num_messages += 1
        self.parts.append(_MESSAGE_HEAD(Opcode.MESSAGE, 22 + len(data), channel_id, sequence, log_time, publish_time))
        self.parts.append(data)
        self.count += 31 + len(data)

    def add_message(self, message) -> None:
        self.add_message_bytes(message.channel_id, message.sequence, message.log_time, message.publish_time,
                               message.data)

    def _record(self, record) -> None:
        b = RecordBuilder()
        record.write(b)
        data = b.end()
        self.parts.append(data)
        self.count += len(data)

    add_channel = add_schema = _record

    def end(self) -> bytes:
        data = b"".join(self.parts)
        self.parts, self.count = [], 0
        return data

    def reset(self) -> None:
        self.parts, self.count, self.num_messages = [], 0, 0
        self.message_start_time = self.message_end_time = 0
        self.message_indices.clear()


class _LeanWriter(Writer):
    """``mcap.writer.Writer`` with a cheaper path for messages into chunks; the file is byte for byte the same.

    Each message's record is packed once and its payload referenced, not copied, until the chunk is
    joined (one copy), compressed and written straight to the file; the library's path copied each
    payload three more times (into its chunk buffer, the chunk record, the output buffer) and built a
    ``Message`` object per message, and two packs per message for its index. Written against mcap
    1.6's ``Writer``, whose name-mangled internals it uses (``_Writer__...``), so pyproject.toml pins
    mcap to 1.6.x (the public ``add_message`` costs 1.71x uncompressed, 1.06x at lz4:
    benchmarks/recording.json). Tests (``tests/test_mcap_files.py``) check every internal it uses and
    compare whole files with the library's for every compression.
    """

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        if self._Writer__enable_data_crcs or self._Writer__chunk_builder is None:
            raise ConfigError("the lean MCAP writer writes chunked files without a data-section CRC")
        self._Writer__chunk_builder = _Chunk()
        self._stats = self._Writer__statistics
        self._compress = {CompressionType.LZ4: "lz4", CompressionType.ZSTD: "zstd"}.get(
            self._Writer__compression, "")

    def add_message(self, channel_id: int, log_time: int, data: bytes, publish_time: int, sequence: int = 0):
        st = self._stats
        if st.message_count == 0:
            st.message_start_time = log_time
        elif log_time < st.message_start_time:
            st.message_start_time = log_time
        if log_time > st.message_end_time:
            st.message_end_time = log_time
        st.channel_message_counts[channel_id] += 1
        st.message_count += 1
        chunk = self._Writer__chunk_builder
        chunk.add_message_bytes(channel_id, sequence, log_time, publish_time, data)
        if chunk.count > self._Writer__chunk_size:
            self._Writer__finalize_chunk()

    def _Writer__finalize_chunk(self) -> None:
        """As the library's ``__finalize_chunk``, writing the compressed chunk to the file without copying it."""
        chunk = self._Writer__chunk_builder
        if chunk.num_messages == 0:
            return
        self._stats.chunk_count += 1
        data = chunk.end()
        if self._compress == "lz4":
            import lz4.frame

            compressed = lz4.frame.compress(data)
        elif self._compress == "zstd":
            import zstandard

            compressed = zstandard.compress(data)
        else:
            compressed = data
        name = self._compress.encode()
        crc = crc32(data) if self._Writer__enable_crcs else 0
        self._Writer__flush()
        stream = self._Writer__stream
        start = stream.tell()
        length = 8 * 3 + 4 + 4 + len(name) + 8 + len(compressed)
        stream.write(_CHUNK_HEAD(Opcode.CHUNK, length, chunk.message_start_time, chunk.message_end_time, len(data), crc)
                     + len(name).to_bytes(4, "little") + name + len(compressed).to_bytes(8, "little"))
        stream.write(compressed)
        index = ChunkIndex(message_start_time=chunk.message_start_time, message_end_time=chunk.message_end_time,
                           chunk_start_offset=start, chunk_length=9 + length, message_index_offsets={},
                           message_index_length=0, compression=self._compress, compressed_size=len(compressed),
                           uncompressed_size=len(data))
        index_start = start + 9 + length
        builder = self._Writer__record_builder
        if self._Writer__index_types & IndexType.MESSAGE:
            # Each as mcap.records.MessageIndex.write lays it out, in one pack instead of two per message.
            for cid, flat in chunk.message_indices.items():
                index.message_index_offsets[cid] = index_start + builder.count
                builder.write(struct.pack(f"<BQHI{len(flat)}Q", Opcode.MESSAGE_INDEX, 6 + 8 * len(flat), cid,
                                          8 * len(flat), *flat))
        index.message_index_length = builder.count
        self._Writer__flush()
        self._Writer__chunk_indices.append(index)
        chunk.reset()


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
    whole : bool
        Write to ``<path>.partial`` and rename to ``path`` only when
        :meth:`close` has finished it (one-shot outputs: convert, transcode):
        a file at ``path`` is then always complete. An exception inside a
        ``with`` block removes the partial file. Recordings leave it False:
        a killed recorder's file must be readable under its own name.

    A write that fails (a full disk) raises one :class:`TransportError`
    saying how many messages are in the file (those up to the last
    successful :meth:`flush`); the writer then only closes its handle.
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
        whole: bool = False,
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
        self.whole = bool(whole)
        self._target = self.path.with_name(self.path.name + ".partial") if self.whole else self.path
        if self.whole and self.path.exists():
            raise TransportError(f"cannot create {self.path}: it exists (outputs are never overwritten)")
        try:
            if self.whole:
                self._target.unlink(missing_ok=True)  # a previous run's leftover, never a finished file
            self._file = open(self._target, "xb")
            # Held until the file is closed (or its process dies): readers tell a file being written from one
            # whose writer died (recovery.being_written).
            fcntl.flock(self._file.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as exc:
            raise TransportError(f"cannot create {self._target}: {exc}") from None
        self._fsync = fsync
        self.messages_flushed = 0  # messages the file holds for sure: those before the last successful flush
        self.failed: str = ""
        self._schemas: dict[tuple[str, int], int] = {}
        self._json_schemas: dict[str, int] = {}
        self._json_channels: dict[str, int] = {}
        self._channels: dict[tuple[str, str, int, str], int] = {}
        # (topic, schema, version, the envelope's problem) -> channel id: what _channel decides for a message,
        # looked up once per message instead of decided again
        self._channel_of: dict[tuple[str, str, int, str], int] = {}
        self._provenance: tuple[bytes, int] | None = None
        self.messages = 0
        self.json_messages = 0
        self.payload_bytes = 0
        self.unflushed_bytes = 0
        self.invalid = 0
        self.closed = False
        try:
            self._writer = _LeanWriter(self._file, chunk_size=chunk_size_bytes, compression=_COMPRESSION[compression])
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
            if self.whole:
                self._target.unlink(missing_ok=True)
            if isinstance(exc, OSError):
                raise TransportError(f"cannot write {self._target}: {exc}") from None
            raise

    def _failure(self, exc: OSError) -> TransportError:
        """Note a failed write (the file stays as the disk left it) and say what the file holds."""
        self.failed = exc.strerror or str(exc)
        lost = self.messages - self.messages_flushed
        held = ("nothing: it is removed" if self.whole else
                f"{self.messages_flushed} messages up to its last flush (more may be in complete chunks; "
                f"`mntes-stream recover` finishes it)")
        return TransportError(f"cannot write {self._target}: {self.failed}; the file holds {held}; "
                              f"{lost} later message(s) may not be in it")

    def _guard(self, call, *args, **kwargs):
        if self.failed:
            raise TransportError(f"cannot write {self._target}: an earlier write failed ({self.failed})")
        try:
            return call(*args, **kwargs)
        except OSError as exc:
            raise self._failure(exc) from None

    # -- channels
    def _channel(self, topic: str, env: Envelope) -> int:
        cid = self._channel_of.get((topic, env.schema, env.version, env.problem))
        if cid is None:
            cid = self._channel_of[(topic, env.schema, env.version, env.problem)] = self._new_channel(topic, env)
        return cid

    def _new_channel(self, topic: str, env: Envelope) -> int:
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

    def write(self, key: str, payload: bytes, log_time_ns: int, env: Envelope | None = None) -> Envelope:
        """Store one received message verbatim; returns what its envelope said.

        ``env``: the payload's :func:`peek_envelope`, when the caller read it already (it is not read twice).
        """
        payload = bytes(payload)
        env = check_provenance(payload, peek_envelope(payload) if env is None else env)
        if env.problem:
            self.invalid += 1
        pub = env.publish_time_ns if env.publish_time_ns is not None and env.publish_time_ns >= 0 else log_time_ns
        seq = (env.seq or 0) & 0xFFFFFFFF
        self.messages += 1  # counted before the write: a failed write is among the ones said to be missing
        if self.failed:
            raise TransportError(f"cannot write {self._target}: an earlier write failed ({self.failed})")
        try:  # as _guard, without a closure and a call for every message
            self._writer.add_message(self._channel(str(key), env), log_time=int(log_time_ns), data=payload,
                                     publish_time=int(pub), sequence=seq)
        except OSError as exc:
            raise self._failure(exc) from None
        self.payload_bytes += len(payload)
        self.unflushed_bytes += len(payload)
        if env.schema == PROVENANCE_SCHEMA and not env.problem and (self._provenance is None or payload != self._provenance[0]):
            self._guard(self._add_provenance, payload, log_time_ns)
        return env

    def write_json(self, topic: str, schema_name: str, schema: Mapping, message: Mapping, log_time_ns: int) -> None:
        """One json message (encoding ``json``, its JSON Schema registered once as ``jsonschema``), e.g. the
        Foxglove channels of ``mntes_stream.foxglove.translate`` beside the msgpack originals."""
        self._guard(self._write_json, topic, schema_name, schema, message, log_time_ns)

    def _write_json(self, topic: str, schema_name: str, schema: Mapping, message: Mapping, log_time_ns: int) -> None:
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
        self._guard(self._writer.add_attachment, create_time=int(create_time_ns), log_time=int(log_time_ns), name=name,
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
        self._guard(self._writer.add_metadata, name, {str(k): str(v) for k, v in data.items()})

    def flush(self) -> None:
        """Close the open chunk and hand everything to the OS (and the disk if ``fsync``)."""
        self._guard(self._flush)

    def _flush(self) -> None:
        self._writer.flush()
        if self._fsync:
            os.fsync(self._file.fileno())
        self.unflushed_bytes = 0
        self.messages_flushed = self.messages

    def close(self) -> None:
        """Finish the file (summary, indexes, footer) and close it; a ``whole`` file then gets its name.

        After a failed write only the handle is closed (nothing more is written), and a ``whole``
        file's partial file is removed.
        """
        if self.closed:
            return
        self.closed = True
        if self.failed:
            self.abort()
            return
        try:
            self._guard(self._finish)
        except BaseException:
            self.abort()
            raise
        if self.whole:
            try:
                if self.path.exists():
                    raise TransportError(f"cannot create {self.path}: it appeared while writing (never overwritten)")
                os.replace(self._target, self.path)
            except OSError as exc:
                raise TransportError(f"cannot rename {self._target} to {self.path}: {exc}") from None
            finally:
                self._target.unlink(missing_ok=True)

    def _finish(self) -> None:
        try:
            self._writer.finish()
            self._file.flush()
            if self._fsync or self.whole:
                os.fsync(self._file.fileno())
            self.messages_flushed = self.messages
        finally:
            with contextlib.suppress(OSError):  # after a failed write the buffer is unwritable: said already
                self._file.close()

    def abort(self) -> None:
        """Close the handle without finishing; a ``whole`` file's partial file is removed."""
        self.closed = True
        with contextlib.suppress(OSError):
            self._file.close()
        if self.whole:
            self._target.unlink(missing_ok=True)

    def __enter__(self):
        return self

    def __exit__(self, exc_type, *exc):
        if exc_type is not None and self.whole:
            self.abort()  # an output that stopped half way must not look finished
        else:
            self.close()

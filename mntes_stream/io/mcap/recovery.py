"""Indexing MCAP files, finished or not: every complete chunk of a file whose writer died is kept."""

from __future__ import annotations

import io
import struct
import zlib
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

from mcap.data_stream import ReadDataStream
from mcap.opcode import Opcode
from mcap.records import Channel, Chunk, Message, Schema

from mntes_stream.errors import TransportError

_MAGIC = b"\x89MCAP0\r\n"
_RECORD_HEADER = struct.Struct("<BQ")


class TruncatedFileWarning(UserWarning):
    """A file was not finished by its writer; its complete chunks were recovered."""



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
    record: Channel  # as written: what a rewrite of the file copies


@dataclass
class FileIndex:
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
        self.channels[ch.id] = _ChannelInfo(ch.topic, name, version, ch)

    def info(self) -> FileInfo:
        msgs = sum(self.counts.values())
        starts = [c.start_ns for c in self.chunks] + [m.log_time for m in self.loose]
        ends = [c.end_ns for c in self.chunks] + [m.log_time for m in self.loose]
        return FileInfo(
            str(self.path), self.complete, self.problem, self.size, self.recovered,
            len(self.chunks), msgs, min(starts, default=None), max(ends, default=None),
        )


def chunk_records(chunk: Chunk, messages: bool = True) -> Iterator[Schema | Channel | Message]:
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


def read_record(f, offset: int, length: int, expect: int) -> ReadDataStream:
    f.seek(offset)
    raw = f.read(length)
    if len(raw) != length or raw[0] != expect:
        raise TransportError(f"record at offset {offset} is not opcode {expect:#x}")
    return ReadDataStream(io.BytesIO(raw[9:]))


def index_from_summary(idx: FileIndex, f) -> bool:
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


def index_by_scan(idx: FileIndex, f) -> None:
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
                for rec in chunk_records(chunk):
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


def index_file(path: Path) -> FileIndex:
    try:
        size = path.stat().st_size
        f = open(path, "rb")
    except OSError as exc:
        raise TransportError(f"cannot read {path}: {exc}") from None
    idx = FileIndex(path=path, size=size)
    with f:
        head = f.read(len(_MAGIC))
        if head != _MAGIC[: len(head)]:
            raise TransportError(f"{path} is not an MCAP file (bad magic)")
        if len(head) < len(_MAGIC):
            idx.problem = "file shorter than the MCAP magic"
            return idx
        if not index_from_summary(idx, f):
            index_by_scan(idx, f)
    return idx

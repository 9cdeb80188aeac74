"""Checking every chunk of a recording (``inspect --verify``) and rewriting a killed one whole (``recover``).

A file whose writer died has no summary or footer: the recovering reader
(:mod:`.recovery`) reads it, other MCAP readers (python ``make_reader``,
Foxglove) may not. :func:`recover_file` writes every readable record into a
new, finished file with index and footer. :func:`verify_file` decompresses
every chunk and checks its CRC, so a file is called readable only when it is.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from mcap.opcode import Opcode
from mcap.records import Attachment, Channel, Chunk, Message, Metadata, Schema
from mcap.writer import CompressionType, Writer

from mntes_stream import __version__
from mntes_stream.errors import TransportError
from mntes_stream.io.mcap.recovery import FileIndex, chunk_records, index_file, read_record

__all__ = ["FileCheck", "recover_file", "verify_file"]


@dataclass(frozen=True)
class FileCheck:
    """What a full read of one file found.

    ``readable_messages`` counts messages in chunks that passed their CRC
    (and loose messages); ``damaged_chunks`` lists ``(byte offset, why)`` of
    every unreadable chunk (and, for :func:`recover_file`, unreadable
    metadata or attachment records).
    """

    path: str
    complete: bool
    chunks: int
    damaged_chunks: tuple[tuple[int, str], ...]
    readable_messages: int

    @property
    def ok(self) -> bool:
        return self.complete and not self.damaged_chunks


def _chunks(ix: FileIndex, f):
    """``(offset, records or None, why)`` for every indexed chunk, in file order."""
    for ref in sorted(ix.chunks, key=lambda c: c.offset):
        try:
            chunk = Chunk.read(read_record(f, ref.offset, ref.length, Opcode.CHUNK))
            yield ref.offset, list(chunk_records(chunk)), ""
        except Exception as exc:  # CRC, size, framing: the chunk is unreadable, the rest may not be
            yield ref.offset, None, str(exc) or type(exc).__name__


def verify_file(path: str | Path) -> FileCheck:
    """Read every chunk of ``path`` (CRC checked); TransportError if it is not MCAP at all."""
    ix = index_file(Path(path))
    damaged, readable = [], len(ix.loose)
    with open(ix.path, "rb") as f:
        for offset, records, why in _chunks(ix, f):
            if records is None:
                damaged.append((offset, why))
            else:
                readable += sum(isinstance(r, Message) for r in records)
    return FileCheck(str(ix.path), ix.complete, len(ix.chunks), tuple(damaged), readable)


def recover_file(src: str | Path, dst: str | Path, compression: str = "zstd") -> FileCheck:
    """Write every readable record of ``src`` into a new finished file ``dst`` (not overwritten).

    Returns what was found in ``src``; ``dst`` holds its ``readable_messages``.
    """
    ix = index_file(Path(src))
    dst = Path(dst)
    try:
        out = open(dst, "xb")
    except OSError as exc:
        raise TransportError(f"cannot create {dst}: {exc}") from None
    damaged, readable = [], 0
    kinds = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}
    with out, open(ix.path, "rb") as f:
        w = Writer(out, compression=kinds[compression])
        w.start(profile="", library=f"mntes-stream {__version__} recover")
        schema_ids: dict[int, int] = {}
        channel_ids: dict[int, int] = {}

        def schema(rec: Schema) -> None:
            if rec.id not in schema_ids:
                schema_ids[rec.id] = w.register_schema(rec.name, rec.encoding, rec.data)

        def channel(rec: Channel) -> None:
            if rec.id not in channel_ids:
                sid = schema_ids.get(rec.schema_id, 0)
                channel_ids[rec.id] = w.register_channel(rec.topic, rec.message_encoding, sid, dict(rec.metadata or {}))

        def message(rec: Message) -> int:
            cid = channel_ids.get(rec.channel_id)
            if cid is None:  # its channel was defined in a damaged chunk: cannot be labelled
                return 0
            w.add_message(cid, log_time=rec.log_time, data=rec.data, publish_time=rec.publish_time,
                          sequence=rec.sequence)
            return 1

        for rec in ix.schemas.values():
            schema(rec)
        for info in ix.channels.values():
            channel(info.record)
        for offset, records, why in _chunks(ix, f):
            if records is None:
                damaged.append((offset, why))
                continue
            for rec in records:
                if isinstance(rec, Schema):
                    schema(rec)
                elif isinstance(rec, Channel):
                    channel(rec)
                else:
                    readable += message(rec)
        readable += sum(message(m) for m in ix.loose)
        for off, length in ix.metadata:
            try:
                m = Metadata.read(read_record(f, off, length, Opcode.METADATA))
            except Exception as exc:  # no CRC on these records: a damaged one is reported, not copied
                damaged.append((off, f"metadata record unreadable: {exc}"))
                continue
            w.add_metadata(m.name, dict(m.metadata))
        for off, length in ix.attachments:
            try:
                a = Attachment.read(read_record(f, off, length, Opcode.ATTACHMENT))
            except Exception as exc:
                damaged.append((off, f"attachment unreadable: {exc}"))
                continue
            w.add_attachment(create_time=a.create_time, log_time=a.log_time, name=a.name, media_type=a.media_type,
                             data=a.data)
        w.finish()
    return FileCheck(str(ix.path), ix.complete, len(ix.chunks), tuple(damaged), readable)

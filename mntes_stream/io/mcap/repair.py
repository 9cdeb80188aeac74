"""Checking every chunk of a recording (``inspect --verify``) and rewriting a killed one whole (``recover``).

A file whose writer died has no summary or footer: the recovering reader
(:mod:`.recovery`) reads it, other MCAP readers (python ``make_reader``,
Foxglove) may not. :func:`recover_file` writes every readable record into a
new, finished file with index and footer. :func:`verify_file` decompresses
every chunk and checks its CRC, so a file is called readable only when it is.
Both describe every damaged chunk (:class:`~.recovery.DamagedChunk`: byte
offset, why, time span, messages and topics it held).
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path

from mcap.opcode import Opcode
from mcap.records import Attachment, Channel, Chunk, Message, Metadata, Schema
from mcap.writer import CompressionType, Writer

from mntes_stream import __version__
from mntes_stream.errors import TransportError
from mntes_stream.io.mcap.recovery import (
    DamagedChunk,
    FileIndex,
    chunk_records,
    damage_at,
    index_by_scan,
    index_file,
    read_record,
)

__all__ = ["DAMAGE_METADATA", "FileCheck", "damage_metadata", "recover_file", "verify_file"]

# The metadata record that marks what an output could not contain (recover, convert).
DAMAGE_METADATA = "mntes.damaged"


@dataclass(frozen=True)
class FileCheck:
    """What a full read of one file found.

    ``readable_messages`` counts messages in chunks that passed their CRC
    (and loose messages) and have a channel; ``damaged_chunks`` lists
    ``(byte offset, why)`` of everything unreadable: chunks, a chunk cut by
    the end of the file, a damaged record that stopped the scan, metadata or
    attachment records. ``damage`` describes the chunks (time span,
    messages, topics); ``unlabelled_messages`` were readable but their
    channel record is lost and their payloads do not name their key.
    """

    path: str
    complete: bool
    chunks: int
    damaged_chunks: tuple[tuple[int, str], ...]
    readable_messages: int
    damage: tuple[DamagedChunk, ...] = ()
    unlabelled_messages: int = 0
    reconstructed_channels: tuple[str, ...] = ()

    @property
    def ok(self) -> bool:
        """Every record was read (a file whose writer died may still be ok: it ends at a record boundary)."""
        return not self.damaged_chunks and not self.unlabelled_messages

    @property
    def lost_messages(self) -> int:
        """Messages known lost (damaged chunks whose message index survived, unlabelled ones)."""
        return sum(d.messages or 0 for d in self.damage) + self.unlabelled_messages

    @property
    def unknown_chunks(self) -> int:
        """Damaged chunks whose message count is unknown (cut by the end of the file)."""
        return sum(d.messages is None for d in self.damage)

    def summary(self) -> str:
        """One line: what was read and what was not."""
        if self.ok:
            return f"{self.readable_messages} messages in {self.chunks} chunks, every chunk read"
        unknown = f" + {self.unknown_chunks} chunk(s) of unknown size" if self.unknown_chunks else ""
        return (f"{self.readable_messages} messages readable; LOST {self.lost_messages} messages{unknown} in "
                f"{len(self.damaged_chunks)} damaged record(s)"
                + (f" ({self.unlabelled_messages} without a channel)" if self.unlabelled_messages else ""))


def _chunks(ix: FileIndex, f):
    """``(ref, records or None, why)`` for every indexed chunk, in file order."""
    for ref in sorted(ix.chunks, key=lambda c: c.offset):
        try:
            chunk = Chunk.read(read_record(f, ref.offset, ref.length, Opcode.CHUNK))
            yield ref, list(chunk_records(chunk)), ""
        except Exception as exc:  # CRC, size, framing: the chunk is unreadable, the rest may not be
            yield ref, None, str(exc) or type(exc).__name__


def _reconstructed(ix: FileIndex) -> tuple[str, ...]:
    from mntes_stream.io.mcap.recovery import RECONSTRUCTED

    return tuple(sorted(c.topic for c in ix.channels.values() if RECONSTRUCTED in (c.record.metadata or {})))


def _walk(ix: FileIndex, f) -> tuple[list[DamagedChunk], list[tuple[int, str]], int]:
    """Read a finished file record by record too, as a killed one is read: what its summary reads past.

    A damaged length field, record header or message index, which the
    summary's chunk index steps over and a streaming reader cannot, is found
    here, and so is a summary that disagrees with the chunks. Returns the
    damaged chunks, the damaged records and the readable messages.
    """
    walked = FileIndex(path=ix.path, size=ix.size)
    walked.schemas.update(ix.schemas)  # channels whose record is in a damaged chunk stay known by the summary
    walked.channels.update(ix.channels)
    index_by_scan(walked, f)
    bad = list(walked.bad_records)
    readable = walked.info().messages
    refs = {c.offset: c for c in ix.chunks}
    lost = []
    for d in walked.damage():
        try:  # a chunk whose header the walk cannot trust may still be read through the summary's chunk index
            chunk = Chunk.read(read_record(f, d.offset, refs[d.offset].length, Opcode.CHUNK))
            readable += sum(isinstance(r, Message) for r in chunk_records(chunk))
        except Exception:  # not indexed there, or unreadable that way too (CRC, size, framing): lost
            lost.append(d)
        else:
            bad.append((d.offset, f"{d.why}; read through the summary's chunk index, nothing lost"))
    seen = {c.offset for c in walked.chunks} | {d.offset for d in walked.damaged}
    bad += [(c.offset, "the summary's chunk index points here, but no chunk record was found here")
            for c in ix.chunks if c.offset not in seen]
    said, held = sum(ix.counts.values()), sum(walked.counts.values())
    if not walked.damaged and said != held:
        bad.append((ix.size, f"the summary's statistics say {said} messages, the chunks hold {held}"))
    return lost, bad, readable


def _check(ix: FileIndex, found: list[DamagedChunk], bad_records: list[tuple[int, str]], readable: int) -> FileCheck:
    damage = list({d.offset: d for d in [*ix.damage(), *found]}.values())  # found by reading and by walking: once
    chunks = {d.offset for d in damage}  # a damaged header of a lost chunk is said once, with the chunk
    damaged = [(d.offset, d.why) for d in damage] + sorted({r for r in ix.bad_records + bad_records if r[0] not in chunks})
    return FileCheck(str(ix.path), ix.complete, len(ix.chunks) + len(ix.damaged), tuple(sorted(damaged)), readable,
                     tuple(sorted(damage, key=lambda d: d.offset)), sum(ix.unlabelled.values()), _reconstructed(ix))


def verify_file(path: str | Path) -> FileCheck:
    """Read every chunk, metadata and attachment record of ``path`` (CRC checked).

    TransportError if it is not MCAP at all.
    """
    ix = index_file(Path(path))
    found, bad, readable = [], [], 0
    with open(ix.path, "rb") as f:
        if ix.complete:  # every chunk is read by the walk (a killed file's index was made by one)
            found, bad, readable = _walk(ix, f)
        else:
            readable += sum(m.channel_id in ix.channels for m in ix.loose)
            for ref, records, why in _chunks(ix, f):
                if records is None:
                    found.append(damage_at(ix, f, ref, why))
                else:
                    readable += sum(isinstance(r, Message) and r.channel_id in ix.channels for r in records)
        for which, opcode, read in (("metadata", Opcode.METADATA, Metadata.read),
                                    ("attachments", Opcode.ATTACHMENT, Attachment.read)):
            for off, length in getattr(ix, which):
                try:
                    read(read_record(f, off, length, opcode))
                except Exception as exc:  # no CRC on these records: a damaged one is unreadable
                    bad.append((off, f"{which} record unreadable: {exc}"))
    return _check(ix, found, bad, readable)


def damage_metadata(damage, unlabelled: int = 0) -> dict[str, str]:
    """The ``mntes.damaged`` metadata record: what an output could not contain, and when."""
    damage = list(damage)
    return {
        "chunks": str(len(damage)),
        "messages_lost": str(sum(d.messages or 0 for d in damage) + unlabelled),
        "chunks_of_unknown_size": str(sum(d.messages is None for d in damage)),
        "unlabelled_messages": str(unlabelled),
        "spans_ns": json.dumps([[d.start_ns, d.end_ns] for d in damage]),
        "detail": json.dumps([{"file": d.path, "offset": d.offset, "why": d.why, "start_ns": d.start_ns,
                               "end_ns": d.end_ns, "messages": d.messages, "topics": dict(d.topics)}
                              for d in damage]),
    }


def partial_path(dst: Path) -> Path:
    """Where an output is written until it is whole: same directory, renamed at the end."""
    return dst.with_name(dst.name + ".partial")


def recover_file(src: str | Path, dst: str | Path, compression: str = "zstd") -> FileCheck:
    """Write every readable record of ``src`` into a new finished file ``dst`` (not overwritten).

    ``dst`` appears only when finished (it is written as ``dst.partial`` and
    renamed). Returns what was found in ``src``; ``dst`` holds its
    ``readable_messages``, channels rebuilt for messages whose channel record
    was lost, and a ``mntes.damaged`` metadata record when anything was.
    """
    ix = index_file(Path(src))
    dst = Path(dst)
    if dst.exists():
        raise TransportError(f"cannot create {dst}: it exists (recover never overwrites)")
    tmp = partial_path(dst)
    try:
        tmp.unlink(missing_ok=True)  # a previous run's leftover: never a finished file
        out = open(tmp, "xb")
    except OSError as exc:
        raise TransportError(f"cannot create {tmp}: {exc}") from None
    found, bad, readable = [], [], 0
    kinds = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}
    try:
        with out, open(ix.path, "rb") as f:
            if ix.complete:  # what its summary reads past (its messages are read through the summary below)
                found, bad, _ = _walk(ix, f)
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
                    channel_ids[rec.id] = w.register_channel(rec.topic, rec.message_encoding, sid,
                                                             dict(rec.metadata or {}))

            def message(rec: Message) -> int:
                cid = channel_ids.get(rec.channel_id)
                if cid is None:  # channel lost and not rebuilt: counted in ix.unlabelled
                    return 0
                w.add_message(cid, log_time=rec.log_time, data=rec.data, publish_time=rec.publish_time,
                              sequence=rec.sequence)
                return 1

            for rec in ix.schemas.values():
                schema(rec)
            for info in ix.channels.values():
                channel(info.record)
            for ref, records, why in _chunks(ix, f):
                if records is None:
                    found.append(damage_at(ix, f, ref, why))
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
                    bad.append((off, f"metadata record unreadable: {exc}"))
                    continue
                w.add_metadata(m.name, dict(m.metadata))
            for off, length in ix.attachments:
                try:
                    a = Attachment.read(read_record(f, off, length, Opcode.ATTACHMENT))
                except Exception as exc:
                    bad.append((off, f"attachment unreadable: {exc}"))
                    continue
                w.add_attachment(create_time=a.create_time, log_time=a.log_time, name=a.name,
                                 media_type=a.media_type, data=a.data)
            check = _check(ix, found, bad, readable)
            if not check.ok:
                w.add_metadata(DAMAGE_METADATA, damage_metadata(check.damage, check.unlabelled_messages)
                               | {"source": str(ix.path), "records": json.dumps(check.damaged_chunks)})
            w.finish()
            out.flush()
            os.fsync(out.fileno())
        if dst.exists():
            raise TransportError(f"cannot create {dst}: it appeared while recovering (recover never overwrites)")
        os.replace(tmp, dst)
    except OSError as exc:  # disk full, ...: no file that looks finished
        tmp.unlink(missing_ok=True)
        raise TransportError(f"cannot write {dst}: {exc.strerror or exc}") from None
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return check

"""Indexing MCAP files, finished or not: every complete chunk of a file whose writer died is kept.

What cannot be read is described, never silently passed over: a damaged chunk
(CRC, size, compression) or one cut by the end of the file is a
:class:`DamagedChunk` with its time span (from the chunk record's header,
which precedes the compressed body) and the messages and channels it held
(from the message index records that follow it in the file, or that the
summary points to). Messages whose channel record was in a damaged chunk keep
a channel rebuilt from their own payloads (an mntes envelope names its setup,
board, module or sensor, so its key), marked ``mntes.reconstructed``.

Damage in the middle of a file is not taken for its end: the walk
(:func:`index_by_scan`) checks each record's length against its own fields
and resynchronises on the next valid chunk (:func:`next_chunk`), naming the
skipped span; only a chunk that overruns the end with nothing valid after it
is a cut tail.
"""

from __future__ import annotations

import io
import re
import struct
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

from mcap.data_stream import ReadDataStream
from mcap.opcode import Opcode
from mcap.records import Attachment, Channel, Chunk, DataEnd, Header, Message, Metadata, Schema
from zlib_ng.zlib_ng import crc32  # zlib's CRC, 9x faster (pyproject.toml)

from mntes_stream.errors import TransportError

_MAGIC = b"\x89MCAP0\r\n"
_RECORD_HEADER = struct.Struct("<BQ")
_TIMES = struct.Struct("<QQ")  # a chunk body starts with message_start_time, message_end_time
_INDEX_HEAD = struct.Struct("<HI")  # a message index body: channel id, byte length of its (time, offset) pairs
_PAIR = struct.Struct("<QQ")
_CHUNK_FIXED = struct.Struct("<QQQII")  # a chunk body: start, end, uncompressed size, CRC, compression length
_COMPRESSIONS = frozenset({"", "zstd", "lz4"})  # what chunk_records reads
_OPCODES = frozenset(int(o) for o in Opcode)
_HEAD = 64  # bytes enough for a record header and a chunk's fields up to its data length
_WINDOW = 1 << 22  # bytes searched at a time when resynchronising
# A chunk record's start: opcode, 8-byte length, 36 bytes of times, size and CRC, then its compression string.
_ANCHOR = re.compile(rb"\x06.{36}(?:\x00\x00\x00\x00|\x04\x00\x00\x00zstd|\x03\x00\x00\x00lz4)", re.S)
_TAG = re.compile(rb"\x04\x00\x00\x00zstd|\x03\x00\x00\x00lz4")  # a compressed chunk's compression field
_INDEX_OPCODE = re.compile(rb"\x07")
# Records of the summary section only (MCAP spec): before the data end record, one is a damaged opcode (a message
# index whose opcode byte was hit reads as a summary offset, and would be skipped unseen).
_SUMMARY_ONLY = frozenset({Opcode.CHUNK_INDEX, Opcode.ATTACHMENT_INDEX, Opcode.STATISTICS, Opcode.METADATA_INDEX,
                           Opcode.SUMMARY_OFFSET})
# Records whose fields say how long they are (mcap's own parsers): checked against their length field.
_WHOLE = {Opcode.HEADER: Header.read, Opcode.SCHEMA: Schema.read, Opcode.CHANNEL: Channel.read,
          Opcode.METADATA: Metadata.read, Opcode.ATTACHMENT: Attachment.read, Opcode.DATA_END: DataEnd.read}
RECONSTRUCTED = "mntes.reconstructed"


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
    damaged_chunks: int = 0  # known at indexing (unfinished files); a finished file's are found on reading
    damaged_messages: int = 0  # messages those chunks held, where their message index says
    unlabelled_messages: int = 0  # readable messages whose channel is lost and could not be rebuilt
    # (byte offset, why) of damaged records that held no lost chunk (a chunk's length field, index records)
    damaged_records: tuple[tuple[int, str], ...] = ()


def _utc(t_ns: int | None) -> str:
    if t_ns is None:
        return "?"
    s, ns = divmod(int(t_ns), 1_000_000_000)
    return time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(s)) + f".{ns // 1_000_000:03d}Z"


@dataclass(frozen=True, slots=True)
class DamagedChunk:
    """A chunk that could not be read, and what it held.

    ``messages`` is None when unknown (a chunk cut by the end of the file has
    no message index after it); ``topics`` pairs each topic (or
    ``channel <id>`` when the channel record itself is lost) with its count.
    """

    path: str
    offset: int
    why: str
    start_ns: int | None
    end_ns: int | None
    messages: int | None
    topics: tuple[tuple[str, int], ...] = ()

    def describe(self, with_path: bool = True) -> str:
        held = "an unknown number of messages" if self.messages is None else f"{self.messages} messages"
        topics = ", ".join(f"{t} x{n}" for t, n in self.topics)
        return ((f"{self.path} " if with_path else "") + f"byte {self.offset}: {held}, {_utc(self.start_ns)} .. "
                f"{_utc(self.end_ns)}" + (f" ({topics})" if topics else "") + f": {self.why}")


def damage_line(damage) -> str:
    """One line for a list of :class:`DamagedChunk` ("" when empty): how many, messages lost, time spans."""
    damage = list(damage)
    if not damage:
        return ""
    known = sum(d.messages for d in damage if d.messages is not None)
    unknown = sum(d.messages is None for d in damage)
    spans = "; ".join(f"{_utc(d.start_ns)} .. {_utc(d.end_ns)}" for d in damage[:5])
    more = f" and {len(damage) - 5} more" if len(damage) > 5 else ""
    return (f"{len(damage)} damaged chunk(s), {known} messages lost"
            + (f" (+ {unknown} chunk(s) of unknown size)" if unknown else "") + f", spans {spans}{more}")


@dataclass(slots=True)
class _ChunkRef:
    start_ns: int
    end_ns: int
    offset: int
    length: int
    index_offsets: dict[int, int] = field(default_factory=dict)  # channel id -> offset of its message index


@dataclass(slots=True)
class _Damage:
    offset: int
    why: str
    start_ns: int | None
    end_ns: int | None
    counts: dict[int, int] | None  # channel id -> messages; None: unknown


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
    damaged: list[_Damage] = field(default_factory=list)
    # channel id -> (derived (topic, schema, version) or None, messages, first offset) for messages read
    # before any record of their channel: its record was in a damaged chunk.
    orphans: dict[int, list] = field(default_factory=dict)
    unlabelled: dict[int, int] = field(default_factory=dict)
    # (offset, why) of damaged records that held no chunk: a length field, index or loose records skipped
    bad_records: list[tuple[int, str]] = field(default_factory=list)
    # While scanning: (log time, offset) of the messages per channel of the chunk just read whose message index
    # records are still to come; None when no index record is expected.
    pending: dict[int, list[tuple[int, int]]] | None = None

    def damage(self) -> tuple[DamagedChunk, ...]:
        """Every damaged chunk found so far, with topics named where the channels are known."""
        return tuple(self.describe(d) for d in self.damaged)

    def describe(self, d: _Damage) -> DamagedChunk:
        topics: dict[str, int] = {}
        for cid, n in (d.counts or {}).items():
            ch = self.channels.get(cid)
            name = ch.topic if ch is not None else f"channel {cid} (its record is lost)"
            topics[name] = topics.get(name, 0) + n
        msgs = None if d.counts is None else sum(d.counts.values())
        return DamagedChunk(str(self.path), d.offset, d.why, d.start_ns, d.end_ns, msgs, tuple(sorted(topics.items())))

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
        msgs = sum(self.counts.values()) - sum(self.unlabelled.values())
        starts = [c.start_ns for c in self.chunks] + [m.log_time for m in self.loose]
        ends = [c.end_ns for c in self.chunks] + [m.log_time for m in self.loose]
        return FileInfo(
            str(self.path), self.complete, self.problem, self.size, self.recovered,
            len(self.chunks), msgs, min(starts, default=None), max(ends, default=None),
            len(self.damaged), sum(sum(d.counts.values()) for d in self.damaged if d.counts),
            sum(self.unlabelled.values()), tuple(self.bad_records),
        )


def chunk_records(chunk: Chunk, messages: bool = True, offsets: list[int] | None = None
                  ) -> Iterator[Schema | Channel | Message]:
    """Decompress one chunk (checking its CRC) and yield its records.

    ``offsets`` gets the offset of each message record yielded in the
    uncompressed chunk (what its message index records point to).
    """
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
    if chunk.uncompressed_crc and crc32(data) != chunk.uncompressed_crc:
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
                if offsets is not None:
                    offsets.append(body_start - 9)
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
        _ChunkRef(ci.message_start_time, ci.message_end_time, ci.chunk_start_offset, ci.chunk_length,
                  dict(ci.message_index_offsets))
        for ci in summary.chunk_indexes
    ]
    idx.counts = dict(stats.channel_message_counts)
    idx.attachments = [(a.offset, a.length) for a in summary.attachment_indexes]
    idx.metadata = [(m.offset, m.length) for m in summary.metadata_indexes]
    idx.complete = True
    idx.recovered = idx.size
    return True


def _chunk_times(body: bytes) -> tuple[int | None, int | None]:
    """The message time span in a chunk's header: readable even when its compressed records are not."""
    return _TIMES.unpack_from(body) if len(body) >= _TIMES.size else (None, None)


def _index_count(body: bytes) -> tuple[int, int] | None:
    """``(channel id, messages)`` of a message index record's body, or None if it is too short or not whole pairs."""
    if len(body) < _INDEX_HEAD.size:
        return None
    cid, nbytes = _INDEX_HEAD.unpack_from(body)
    return (cid, nbytes // 16) if nbytes % 16 == 0 else None  # (time, offset) pairs of 16 bytes


def _index_entries(body: bytes) -> list[tuple[int, int]]:
    """The (log time, offset) pairs of a message index record's body that :func:`_index_count` accepted.

    struct rather than mcap's MessageIndex.read: that reads each pair in Python, a third of a scan's time.
    """
    return list(_PAIR.iter_unpack(body[_INDEX_HEAD.size:]))


def damage_at(idx: FileIndex, f, ref: _ChunkRef, why: str) -> DamagedChunk:
    """Describe an indexed chunk that failed to read, from the summary's message index offsets."""
    counts: dict[int, int] = {}
    for off in ref.index_offsets.values():
        try:
            f.seek(off)
            hdr = f.read(9)
            opcode, length = _RECORD_HEADER.unpack(hdr)
            got = _index_count(f.read(min(length, _INDEX_HEAD.size))) if opcode == Opcode.MESSAGE_INDEX else None
        except (OSError, struct.error):
            got = None
        if got is not None:
            counts[got[0]] = counts.get(got[0], 0) + got[1]
    d = _Damage(ref.offset, why, ref.start_ns, ref.end_ns, counts if ref.index_offsets and counts else None)
    return idx.describe(d)


def _note_orphan(idx: FileIndex, rec: Message, offset: int) -> None:
    """A message read before any record of its channel: remember what its payload says its key is."""
    from mntes_stream.io.mcap.envelope import derived_channel

    got = derived_channel(rec.data)
    entry = idx.orphans.get(rec.channel_id)
    if entry is None:
        idx.orphans[rec.channel_id] = [got, 1, offset]
    else:
        if entry[0] != got:  # messages of one channel that disagree: no one label is right for all
            entry[0] = None
        entry[1] += 1


def _rebuild_channels(idx: FileIndex) -> None:
    """Channels for orphaned messages whose payloads all name the same key; the rest stay unlabelled."""
    from mntes_stream.io.mcap.envelope import MESSAGE_ENCODING, SCHEMA_ENCODING, schema_text

    for cid, (got, n, offset) in sorted(idx.orphans.items()):
        if cid in idx.channels:
            continue
        if got is None:
            idx.unlabelled[cid] = n
            continue
        topic, name, version = got
        text = schema_text(name, version)
        sid = 0
        if text is not None:
            sid = next((s.id for s in idx.schemas.values() if s.name == name and bytes(s.data) == text), 0)
            if not sid:
                sid = max(idx.schemas, default=0) + 1
                idx.schemas[sid] = Schema(id=sid, name=name, encoding=SCHEMA_ENCODING, data=text)
        meta = {"mntes.schema": name, "mntes.version": str(version),
                RECONSTRUCTED: f"channel record lost in a damaged chunk; topic read from the {n} payloads "
                               f"(first in the chunk at byte {offset})"}
        idx.add_channel(Channel(id=cid, topic=topic, message_encoding=MESSAGE_ENCODING, schema_id=sid, metadata=meta))


def _chunk_extent(head: bytes, strict: bool = True) -> int | None:
    """The byte length of a chunk record's body by its own fields (``head``: the body's first bytes).

    None when those fields make no sense (compression unknown; ``strict``:
    start after end, which no chunk found by searching may have).
    """
    if len(head) < _CHUNK_FIXED.size:
        return None
    start_ns, end_ns, _, _, clen = _CHUNK_FIXED.unpack_from(head)
    at = _CHUNK_FIXED.size + clen
    if clen > 8 or len(head) < at + 8 or (strict and start_ns > end_ns):
        return None
    try:
        if head[_CHUNK_FIXED.size:at].decode() not in _COMPRESSIONS:
            return None
    except UnicodeDecodeError:
        return None
    return at + 8 + struct.unpack_from("<Q", head, at)[0]


def next_chunk(f, start: int, size: int) -> int | None:
    """Offset of the first chunk record at or after ``start`` whose length field agrees with its own fields.

    The resynchronisation point after a damaged record: a chunk header whose
    length field (8 bytes) equals the length its compression and data-length
    fields give, and which fits the file, does not occur by chance in
    compressed data. Its CRC is checked when it is read.
    """
    pos = start
    while pos < size:
        f.seek(pos)
        buf = f.read(_WINDOW + _HEAD)
        i = 0
        while (m := _ANCHOR.search(buf, i)) is not None and m.start() < _WINDOW:
            j = m.start()
            length = struct.unpack_from("<Q", buf, j + 1)[0]
            if _chunk_extent(buf[j + 9: j + _HEAD]) == length and pos + j + 9 + length <= size:
                return pos + j
            i = j + 1
        pos += _WINDOW
    return None


def _trailing_indexes(f, start: int, stop: int) -> tuple[dict[int, int], int, int | None, int | None] | None:
    """The message index records that end exactly at ``stop``, found backwards from it in ``[start, stop)``.

    Returns ``(messages per channel, offset of the first, first and last log
    time)`` or None when no chain of valid message index records ends there.
    They describe the chunk before them when its own bytes are unreadable.
    """
    lo = max(start, stop - _WINDOW)
    f.seek(lo)
    buf = f.read(stop - lo)
    n = len(buf)
    chain: dict[int, tuple[dict[int, int], list[int]]] = {n: ({}, [])}  # start -> (counts, times) up to the end
    first = None
    for i in sorted((m.start() for m in _INDEX_OPCODE.finditer(buf)), reverse=True):
        if i + 9 + _INDEX_HEAD.size > n:
            continue
        length = struct.unpack_from("<Q", buf, i + 1)[0]
        nxt = i + 9 + length
        if nxt not in chain:
            continue
        got = _index_count(buf[i + 9: nxt])
        if got is None or 6 + 16 * got[1] != length or got[0] in chain[nxt][0]:
            continue
        counts, times = chain[nxt]
        chain[i] = ({**counts, got[0]: got[1]}, times + [t for t, _ in _index_entries(buf[i + 9: nxt])])
        first = i
    if first is None:
        return None
    counts, times = chain[first]
    return counts, lo + first, min(times, default=None), max(times, default=None)


def _whole(opcode: int, body: bytes) -> str:
    """Why ``body`` is not exactly one record of kind ``opcode`` ("" when it is): its fields must fill it."""
    stream = ReadDataStream(io.BytesIO(body))
    _WHOLE[opcode](stream)
    if stream.count != len(body):
        return f"its fields take {stream.count} of its {len(body)} bytes"
    if opcode == Opcode.ATTACHMENT:
        (crc,) = struct.unpack_from("<I", body, len(body) - 4)
        if crc and crc32(body[:-4]) != crc:
            return "attachment CRC mismatch"
    return ""


def _plausible(f, pos: int, size: int) -> bool:
    """Whether a record can start at ``pos``: the end of the file, or a known opcode with a length that fits
    (a consistent chunk header, a message index whose length matches its entries)."""
    if pos >= size:
        return pos == size
    f.seek(pos)
    head = f.read(_HEAD)
    if len(head) < 9:
        return True  # a header cut by the end of the file (a killed writer)
    opcode, length = _RECORD_HEADER.unpack_from(head)
    if pos + 9 + length > size:
        return False
    if opcode == Opcode.CHUNK:
        return _chunk_extent(head[9:]) == length
    if opcode == Opcode.MESSAGE_INDEX:
        got = _index_count(head[9:])
        return got is not None and 6 + 16 * got[1] == length
    if opcode in _WHOLE and length <= _WINDOW:
        f.seek(pos + 9)
        try:
            return not _whole(opcode, f.read(length))
        except Exception:  # mcap raises EndOfFile, struct.error, UnicodeDecodeError...
            return False
    return False  # a loose message or a summary record has nothing to check it by


def _resync(idx: FileIndex, f, pos: int, why: str, times: tuple[int | None, int | None], chunk: bool) -> int | None:
    """Skip a damaged span from ``pos`` to the next valid chunk (None: there is none), naming what it held.

    A span holding a chunk (``chunk``: the damaged record was one, or a
    compression tag is found in it) is a damaged chunk whose messages are
    counted from the message index records at its end when they survive; a
    span of other records is a damaged record.
    """
    q = next_chunk(f, pos + 1, idx.size)
    stop = idx.size if q is None else q
    tail = _trailing_indexes(f, pos, stop) if q is not None else None
    if not chunk:
        f.seek(pos)
        chunk = _TAG.search(f.read(min((tail[1] if tail else stop) - pos, _WINDOW))) is not None
    if not chunk:
        # Right after a chunk read whole, the span may only hold the rest of its index records (their sizes are
        # known: nothing lost); longer, a chunk was in it. Elsewhere, index records ending the span had a chunk.
        rest = sum(9 + _INDEX_HEAD.size + 16 * len(v) for v in (idx.pending or {}).values())
        chunk = stop - pos > rest if idx.pending else tail is not None
    idx.pending = None
    where = (f"bytes {pos}..{stop} skipped, reading resumed at the next valid chunk (byte {q})" if q is not None
             else f"no valid chunk in bytes {pos}..{stop} (the end of the file)")
    if chunk:
        counts = tail[0] if tail else None
        start_ns, end_ns = (tail[2], tail[3]) if tail and tail[2] is not None else times
        idx.damaged.append(_Damage(pos, f"{why}; {where}", start_ns, end_ns, counts))
    else:
        idx.bad_records.append((pos, f"{why}; {where}"))
    idx.problem = f"{why} at byte {pos}; {where}"
    return q


def _scan_chunk(idx: FileIndex, f, pos: int, length: int) -> tuple[int | None, _Damage | None]:
    """Read the chunk record at ``pos``; returns where the next record starts (None: stop) and its damage."""
    size = idx.size
    idx.pending = None
    f.seek(pos + 9)
    head = f.read(_HEAD - 9)
    own = _chunk_extent(head, strict=False)  # its CRC is checked: damaged times are found against its messages
    times = _chunk_times(head)
    times = times if times[0] is not None and times[0] <= times[1] else (None, None)
    if own == length and pos + 9 + length > size:
        # Cut by the end of the file (the chunk being written when the writer died), unless valid chunks follow:
        # then its length is damaged as well as its own fields agree with it.
        q = next_chunk(f, pos + 1, size)
        if q is None:
            idx.problem = f"file ends inside a record (opcode {Opcode.CHUNK:#x}) at byte {pos}"
            idx.damaged.append(_Damage(pos, f"cut by the end of the file at byte {size}", *times, None))
            return None, None
        return _resync(idx, f, pos, f"chunk record of {length} bytes overruns the file", times, True), None
    fixed = ""
    if own != length:
        if own is None or pos + 9 + own > size or not _plausible(f, pos + 9 + own, size):
            said = "unreadable" if own is None else f"{own} bytes"
            return _resync(idx, f, pos, f"chunk record with a damaged length field ({length} bytes; its own "
                                        f"fields: {said})", times, True), None
        fixed = f"chunk record length field says {length} bytes, its own fields {own}: the length field is damaged"
        length = own
    f.seek(pos + 9)
    body = f.read(length)
    try:
        chunk = Chunk.read(ReadDataStream(io.BytesIO(body)))
        offsets: list[int] = []
        records = list(chunk_records(chunk, offsets=offsets))
    except Exception as exc:  # a damaged chunk: described, skipped; the framing after it holds
        why = str(exc) or type(exc).__name__
        if fixed:  # its own fields disagree with its length and its CRC fails: neither can be trusted to frame
            return _resync(idx, f, pos, f"{fixed}; {why}", times, True), None
        damaged = _Damage(pos, f"{fixed}; {why}" if fixed else why, *times, {})
        idx.damaged.append(damaged)
        idx.problem = f"damaged chunk at byte {pos} skipped ({why})"
        return pos + 9 + length, damaged
    if fixed:
        idx.bad_records.append((pos, f"{fixed}; the chunk was read by its own fields (CRC ok), nothing lost"))
    idx.pending = {}
    offsets.reverse()
    for rec in records:
        if isinstance(rec, Schema):
            idx.schemas[rec.id] = rec
        elif isinstance(rec, Channel):
            idx.add_channel(rec)
        else:
            if rec.channel_id not in idx.channels:
                _note_orphan(idx, rec, pos)
            idx.counts[rec.channel_id] = idx.counts.get(rec.channel_id, 0) + 1
            idx.pending.setdefault(rec.channel_id, []).append((rec.log_time, offsets.pop()))
    if idx.pending:
        times = [t for entries in idx.pending.values() for t, _ in entries]
        span = (min(times), max(times))
        if (chunk.message_start_time, chunk.message_end_time) != span:  # no CRC covers the header's fields
            idx.bad_records.append((pos, f"chunk header says its messages span {chunk.message_start_time}.."
                                         f"{chunk.message_end_time} ns, they span {span[0]}..{span[1]} ns: the header "
                                         f"is damaged, nothing lost"))
        idx.chunks.append(_ChunkRef(*span, pos, 9 + length))
    return pos + 9 + length, None


def index_by_scan(idx: FileIndex, f) -> None:
    """Walk the records of a file whose end is missing, keeping every complete one.

    After a damaged record the walk resynchronises on the next valid chunk
    (:func:`next_chunk`): every intact chunk after damage is kept, and the
    skipped span is named (:class:`DamagedChunk` or a damaged record).
    """
    pos = len(_MAGIC)
    size = idx.size
    damaged: _Damage | None = None  # the message index records after a damaged chunk say what it held
    summary = False  # past the data end record
    try:
        while True:
            f.seek(pos)
            hdr = f.read(9)
            if len(hdr) < 9:
                idx.problem = "file ends without a footer" if not hdr else f"file ends inside a record header at byte {pos}"
                break
            opcode, length = _RECORD_HEADER.unpack(hdr)
            end = pos + 9 + length
            if opcode != Opcode.MESSAGE_INDEX:
                _close(damaged)
                damaged = None
                if opcode in _OPCODES:  # an unknown one is damage: what the resync finds is judged by it
                    idx.pending = None
            if opcode == Opcode.CHUNK:
                nxt, damaged = _scan_chunk(idx, f, pos, length)
                if nxt is None:
                    break
                pos = idx.recovered = nxt
                continue
            if not summary and opcode in _SUMMARY_ONLY:
                nxt = _resync(idx, f, pos, f"a summary record (opcode {opcode:#x}) in the data section: a damaged "
                                           "opcode", (None, None), False)
                if nxt is None:
                    break
                pos = idx.recovered = nxt
                continue
            if opcode == Opcode.DATA_END:
                summary = True
            if opcode not in _OPCODES or (opcode == Opcode.HEADER and pos != len(_MAGIC)):
                if opcode >= 0x80 and end <= size and not idx.pending:  # private records (MCAP spec): skipped
                    pos = idx.recovered = end
                    continue
                if _zeros_to_end(f, pos, size):  # preallocated by the filesystem, never written
                    idx.problem = f"file ends with {size - pos} zero bytes from byte {pos} (never written)"
                    break
                nxt = _resync(idx, f, pos, f"not a record (opcode {opcode:#x}, {length} bytes)", (None, None), False)
                if nxt is None:
                    break
                pos = idx.recovered = nxt
                continue
            if opcode == Opcode.MESSAGE_INDEX:  # its own fields say how long it is
                head = f.read(_INDEX_HEAD.size)
                own = 6 + _INDEX_HEAD.unpack(head)[1] if len(head) == _INDEX_HEAD.size else None
                if (own is not None and own != length and own % 16 == 6 and pos + 9 + own <= size
                        and not _plausible(f, end, size) and _plausible(f, pos + 9 + own, size)):
                    idx.bad_records.append((pos, f"message index record length field says {length} bytes, its own "
                                                 f"fields {own}: the length field is damaged"))
                    length, end = own, pos + 9 + own
                f.seek(pos + 9)
            if end > size:
                # A record cut by the end of the file (the writer died), or a damaged length with chunks after it.
                nxt = next_chunk(f, pos + 1, size)
                if nxt is None:
                    idx.problem = f"file ends inside a record (opcode {opcode:#x}) at byte {pos}"
                    break
                pos = idx.recovered = _resync(idx, f, pos, f"record (opcode {opcode:#x}) of {length} bytes "
                                                           f"overruns the file", (None, None), False)
                continue
            if opcode == Opcode.MESSAGE_INDEX:
                body = f.read(length)
                got = _index_count(body)
                if got is None or 6 + 16 * got[1] != length:
                    nxt = _resync(idx, f, pos, f"damaged message index record ({length} bytes)", (None, None), False)
                    if nxt is None:
                        break
                    pos = idx.recovered = nxt
                    continue
                if damaged is not None:
                    damaged.counts[got[0]] = damaged.counts.get(got[0], 0) + got[1]
                elif idx.pending is not None:  # it must point at the messages of the chunk just read
                    entries = _index_entries(body)
                    want = idx.pending.pop(got[0], [])
                    if sorted(entries) != sorted(want):
                        idx.bad_records.append((pos, f"message index record of channel {got[0]} disagrees with the "
                                                     f"chunk before it ({len(entries)} entries for its {len(want)} "
                                                     f"messages of that channel): the index is damaged, nothing lost"))
            elif opcode in _WHOLE or opcode == Opcode.MESSAGE:
                # No CRC on these (but an attachment's): a record whose fields do not fill it exactly is damaged,
                # and so is its length; it is skipped up to the next chunk. A loose message (other writers) has
                # no fields to check its length against.
                body = f.read(length)
                try:
                    rec = Message.read(ReadDataStream(io.BytesIO(body)), length) if opcode == Opcode.MESSAGE else None
                    why = "" if rec is not None else _whole(opcode, body)
                except Exception as exc:  # mcap raises EndOfFile, struct.error, UnicodeDecodeError...
                    why = f"{type(exc).__name__}: {exc}"
                if why:
                    nxt = _resync(idx, f, pos, f"damaged record (opcode {opcode:#x}) ({why})", (None, None), False)
                    if nxt is None:
                        break
                    pos = idx.recovered = nxt
                    continue
                if opcode in (Opcode.SCHEMA, Opcode.CHANNEL):
                    rec = _WHOLE[opcode](ReadDataStream(io.BytesIO(body)))
                if opcode == Opcode.SCHEMA:
                    idx.schemas[rec.id] = rec
                elif opcode == Opcode.CHANNEL:
                    idx.add_channel(rec)
                elif opcode == Opcode.MESSAGE:
                    if rec.channel_id not in idx.channels:
                        _note_orphan(idx, rec, pos)
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
            pos = idx.recovered = end
    finally:
        _close(damaged)
        _rebuild_channels(idx)


def _zeros_to_end(f, pos: int, size: int) -> bool:
    """Whether every byte from ``pos`` to the end of the file is zero."""
    f.seek(pos)
    while block := f.read(_WINDOW):
        if block.strip(b"\0"):
            return False
    return True


def _close(damaged: _Damage | None) -> None:
    """A damaged chunk no message index record followed: what it held is unknown, not zero."""
    if damaged is not None and not damaged.counts:
        damaged.counts = None


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


def file_session(path) -> str:
    """The recording session of a file (its ``mntes.recording`` metadata's ``session``; "" when it has none).

    Reads only the records at the start of the file, where the writer puts that metadata.
    """
    from mcap.stream_reader import StreamReader

    from mntes_stream.io.mcap.envelope import RECORDING_METADATA

    try:
        with open(path, "rb") as f:
            for k, rec in enumerate(StreamReader(f, skip_magic=False).records):
                if isinstance(rec, Metadata) and rec.name == RECORDING_METADATA:
                    return str(rec.metadata.get("session", ""))
                if k > 16:
                    break
    except Exception:  # noqa: BLE001 - not MCAP, damaged at its start: no session to tell
        pass
    return ""


def killed_session(path) -> str:
    """The session of ``path`` if its writer did not finish it (no closing magic: killed), else ""."""
    try:
        with open(path, "rb") as f:
            f.seek(0, 2)
            if f.tell() >= len(_MAGIC) * 2:
                f.seek(-len(_MAGIC), 2)
                if f.read() == _MAGIC:
                    return ""
    except OSError:
        return ""
    return file_session(path)


def being_written(path) -> bool:
    """True while a writer of this package has ``path`` open (it holds an advisory lock until it closes it)."""
    import fcntl

    try:
        with open(path, "rb") as f:
            try:
                fcntl.flock(f.fileno(), fcntl.LOCK_SH | fcntl.LOCK_NB)
            except BlockingIOError:
                return True
            fcntl.flock(f.fileno(), fcntl.LOCK_UN)
    except OSError:
        return False
    return False

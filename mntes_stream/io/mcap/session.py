"""Reading a recorded session (a file, a directory, the folder ``up`` writes, or a list) in time order."""

from __future__ import annotations

import heapq
import re
import warnings
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

from mcap.opcode import Opcode
from mcap.records import Attachment, Chunk, Message, Metadata, Schema

from mntes_stream.errors import TransportError
from mntes_stream.io.mcap.envelope import PROVENANCE_ATTACHMENT
from mntes_stream.io.mcap.recovery import (
    DamagedChunk,
    FileIndex,
    TruncatedFileWarning,
    being_written,
    chunk_records,
    damage_at,
    damage_line,
    file_session,
    index_file,
    read_record,
)


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



def session_files(source: str | Path | Iterable[str | Path]) -> list[Path]:
    """The files of a session, sorted by name within a directory.

    Parameters
    ----------
    source : path, directory, or iterable of them
        An ``.mcap`` file; a directory of them (rotated files); or the folder
        that ``mntes-stream up`` writes, whose files are in ``recordings/``.
    """
    if isinstance(source, (str, Path)):
        p = Path(source)
        if p.is_dir():
            files = sorted(p.glob("*.mcap")) or sorted((p / "recordings").glob("*.mcap"))
            if not files:
                raise TransportError(f"no .mcap files in {p} (nor in {p / 'recordings'})")
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


def _sessions(files: list[Path], index: dict) -> list[tuple[str, list[Path]]]:
    """The files by recording session, oldest first.

    A session is the files of one id, and those of ids recorded over the same span of time: writers that
    ran side by side (a sharded recorder's processes, each naming its own id) are one observation.
    """
    groups: dict[str, list[Path]] = {}
    for p in files:
        groups.setdefault(file_session(p), []).append(p)
    spans = []
    for sid, ps in groups.items():
        infos = [index[p].info() for p in ps]
        starts, ends = [i.start_ns for i in infos], [i.end_ns for i in infos]
        lo = min((t for t in starts if t is not None), default=None)
        hi = max((t for t in ends if t is not None), default=lo)
        spans.append([lo, hi, sid, list(ps)])
    merged: list[list] = []
    for g in spans:  # in the order of their first files (a folder's by name: the order they were written)
        last = merged[-1] if merged else None
        if last is not None and None not in (g[0], g[1], last[0], last[1]) and g[0] <= last[1] and last[0] <= g[1]:
            last[1] = max(last[1], g[1])
            last[3] += g[3]
            last[2] = min(last[2], g[2])  # one name for the writers that ran together
        else:
            merged.append(g)
    order = {p: k for k, p in enumerate(files)}
    return [(sid, sorted(ps, key=order.__getitem__)) for _, _, sid, ps in merged]


class SessionsWarning(UserWarning):
    """The files given hold more than one recording session: the newest is read."""


def _name(source) -> str:
    return str(source) if isinstance(source, (str, Path)) else "the files given"


class Session:
    """One recorded session: a file, a directory, or several (rotated) files.

    Every file a recorder writes names its session (``mntes.recording``
    metadata; a recorder restarted after a crash continues the session of
    the file it left unfinished). Files of several sessions in one folder
    (two ``up`` runs into one ``--out``) are never read as one: the newest
    session is read, with a :class:`SessionsWarning` naming them all, unless
    ``session`` names one (an id or a unique prefix) or is ``"all"``.

    Indexing happens at construction: a finished file is indexed from its
    summary; an unfinished one by walking its records (every complete chunk
    is kept; see :attr:`files` for what was recovered). A file that is not
    MCAP at all raises :class:`TransportError`.

    Parameters
    ----------
    source : path, directory, or iterable of paths
    warn : bool
        Emit a :class:`TruncatedFileWarning` per unfinished file, and a :class:`SessionsWarning`.
    session : str, optional
        The recording session to read: its id or a unique prefix, ``"all"``; default the newest.
    """

    def __init__(self, source, *, warn: bool = True, session: str | None = None):
        files = session_files(source)
        index = {p: index_file(p) for p in files}
        #: ``[(session id, files)]`` found in ``source``, oldest first ("": files of no named session)
        self.sessions = _sessions(files, index)
        if session == "all" or len(self.sessions) == 1:
            chosen = files
        elif session is None:
            chosen = self.sessions[-1][1]
            if warn:
                found = ", ".join(f"{sid or 'unnamed'} ({len(ps)} file(s))" for sid, ps in self.sessions)
                warnings.warn(f"{len(self.sessions)} recording sessions in {_name(source)}: {found}; reading the "
                              f"newest, {self.sessions[-1][0]} (to read another, give its files: `mntes-stream inspect` "
                              "lists them)", SessionsWarning, stacklevel=2)
        else:
            match = [ps for sid, ps in self.sessions if sid == session or (session and sid.startswith(session))]
            if len(match) != 1:
                raise TransportError(f"{'no' if not match else 'more than one'} recording session {session!r} in "
                                     f"{_name(source)}; it has {', '.join(sid or 'unnamed' for sid, _ in self.sessions)}")
            chosen = match[0]
        #: the session read ("all" for every one, "" for files of no named session)
        self.session = "all" if session == "all" and len(self.sessions) > 1 else next(
            sid for sid, ps in self.sessions if chosen[0] in ps)
        self._index = [index[p] for p in chosen]
        self.files = [ix.info() for ix in self._index]
        # Damaged chunks of unfinished files are known now; a finished file's when a read finds them.
        self.damage: list[DamagedChunk] = [d for ix in self._index for d in ix.damage()]
        if warn:
            for fi in self.files:
                if not fi.complete and being_written(fi.path):
                    continue  # a live recording, read up to its last flush: nothing wrong with it
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
                for off, why in fi.damaged_records:
                    warnings.warn(f"{fi.path}: damaged record at byte {off}: {why}", TruncatedFileWarning, stacklevel=3)
            if self.damage:
                warnings.warn(f"damaged: {damage_line(self.damage)}", TruncatedFileWarning, stacklevel=3)

    @property
    def damaged_messages(self) -> int:
        """Messages known lost in the damaged chunks found so far (see :attr:`damage`)."""
        return sum(d.messages or 0 for d in self.damage)

    @property
    def unlabelled_messages(self) -> int:
        """Readable messages skipped because their channel record is lost and could not be rebuilt."""
        return sum(fi.unlabelled_messages for fi in self.files)

    def damage_line(self) -> str:
        """One line on what could not be read ("" when nothing): chunks, messages, time spans."""
        line = damage_line(self.damage)
        if self.unlabelled_messages:
            line = (line + "; " if line else "") + f"{self.unlabelled_messages} messages without a channel skipped"
        return line

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

    def _load(self, ix: FileIndex, fi: int, ref, handles) -> list[Message]:
        if isinstance(ref, list):
            return ref
        f = handles.get(fi)
        if f is None:
            f = handles[fi] = open(ix.path, "rb")
        try:
            chunk = Chunk.read(read_record(f, ref.offset, ref.length, Opcode.CHUNK))
            out = []
            for rec in chunk_records(chunk):
                if isinstance(rec, Message):
                    out.append(rec)
                elif isinstance(rec, Schema):
                    ix.schemas.setdefault(rec.id, rec)
                elif rec.id not in ix.channels:
                    ix.add_channel(rec)
            return out
        except Exception as exc:  # CRC, size, compression: described once, with what it held
            d = damage_at(ix, f, ref, str(exc) or type(exc).__name__)
            if not any(x.path == d.path and x.offset == d.offset for x in self.damage):
                self.damage.append(d)
            warnings.warn(f"damaged chunk skipped: {d.describe()}", TruncatedFileWarning, stacklevel=4)
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
                        rec = read(read_record(f, off, length, opcode), str(ix.path))
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

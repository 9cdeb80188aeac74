"""The ledger of a recording: what the recorder recorded of every stream, and what the converters said of it.

The recorder books every message it writes in a :class:`RecordingBook`: the
counts chunks of each stream (``core.ledger.Ledger("recorded")``: recorded,
duplicate, malformed, never received from the stream's sequence numbers), the
power chunks (converted live or late), and the newest status of every converter
(its own ledger: converted, late, shed, rejected). The sequence numbers of
each stream's recorded counts and power chunks are kept as ranges
(``core.sequence.SeqRanges``), so the counts chunks recorded without their
power (a converter that started late, or was restarted past the sources'
history) are named by number: :meth:`RecordingBook.unpowered`, the
``unpowered`` of every summary. At the close of each file the
book is written as the metadata record ``mntes.ledger`` (:meth:`RecordingBook.metadata`;
strings only, as MCAP metadata is), covering the recorder's run up to that file.
:func:`recording_ledger` reads it back for ``inspect``, or, when a file has
none (a killed recorder writes no closing metadata), recomputes the same book
from the recorded messages.
"""

from __future__ import annotations

import json
from dataclasses import dataclass

import msgpack

from mntes_stream.core.ledger import LOST_MEANS, OTHER, Ledger, stream_order
from mntes_stream.core.sequence import PublisherSequences, SeqRanges, Verdict, format_ranges
from mntes_stream.errors import MntesError
from mntes_stream.io import keys
from mntes_stream.io.mcap.envelope import Envelope, peek_envelope

__all__ = ["LEDGER_METADATA", "RecordingBook", "RecordingLedger", "power_is_late", "recompute_ledger", "recording_ledger",
           "conflict_line", "seqs_from_dict", "unpowered", "unpowered_line"]

LEDGER_METADATA = "mntes.ledger"
_MAX_STREAMS = 100_000  # streams booked by name at most; more (made-up topics) go to core.ledger.OTHER
_MAX_CONVERTERS = 1000
_STATUS_FIELDS = ("chunks_received", "chunks_converted", "chunks_late", "chunks_shed", "chunks_rejected",
                  "chunks_missing", "chunks_set_aside", "chunks_lost", "t_ns")


def power_is_late(payload: bytes) -> bool:
    """Whether a power payload says ``late: true``, read key by key (array values are skipped, not copied)."""
    try:
        u = msgpack.Unpacker(raw=False, strict_map_key=False)
        u.feed(payload)
        for _ in range(u.read_map_header()):
            key = u.unpack()
            if key == "late":
                return u.unpack() is True
            u.skip()
    except Exception:  # a malformed payload is recorded as invalid; it is not late power
        return False
    return False


class RecordingBook:
    """Everything a recording says of its streams, booked message by message (see the module docstring).

    Parameters
    ----------
    setup : str, optional
        Streams of this setup are named ``"<board>/<module>"``; others ``"<setup>:<board>/<module>"``.
    """

    def __init__(self, setup: str | None = None):
        self.setup = setup
        self.ledger = Ledger("recorded")
        self.sequences: dict[str, PublisherSequences] = {}  # counts topic -> its tracker (per publisher, if several)
        self._stream_of: dict[str, str] = {}  # counts topic -> ledger stream
        self._power_stream_of: dict[str, str] = {}  # power topic -> its stream (named once, not per message)
        self.power: dict[str, list[int]] = {}  # stream -> [live, late]
        self.converters: dict[str, dict] = {}  # status service -> its newest ledger and counters
        self.status_topics: dict[str, str] = {}  # status topic -> the service its newest status named
        self.counts_seqs: dict[str, SeqRanges] = {}  # stream -> the numbers of its counts chunks recorded
        self.power_seqs: dict[str, SeqRanges] = {}  # stream -> the numbers of its power chunks recorded (live, late)
        self.restarted: set[str] = set()  # streams whose numbering started over (a source restarted)

    def _stream(self, topic: str) -> str | None:
        parts = topic.split("/")
        if len(parts) != 5 or parts[0] != keys.PREFIX:
            return None
        name = f"{parts[3]}/{parts[4]}"
        return name if self.setup is None or parts[1] == self.setup else f"{parts[1]}:{name}"

    def _bounded(self, stream: str, known) -> str:
        return stream if stream in known or len(known) < _MAX_STREAMS else OTHER

    def add(self, topic: str, payload: bytes, env: Envelope, t_ns: int, late: bool | None = None,
            kind: str | None = None, source: str | None = None) -> Verdict | None:
        """Book one recorded message; returns the counts chunk's :class:`~mntes_stream.core.sequence.Verdict`, else None.

        ``late``: whether a power payload is marked late, when the caller read it already (else read here);
        ``kind``: the topic's ``keys.kind_of``, when the caller knows it (else found here); ``source``: the
        publisher (zenoh id) when the transport says it (two on one stream are numbered apart: ``conflicts``).
        """
        if kind is None:
            kind = keys.kind_of(topic)
        if kind == "counts":
            return self._counts(topic, env, t_ns, source)
        if kind == "power":
            stream = self._power_stream_of.get(topic)
            if stream is None:
                stream = self._stream(topic)
                if stream is not None and len(self._power_stream_of) < _MAX_STREAMS:
                    self._power_stream_of[topic] = stream
            if stream is not None and not env.problem:
                stream = self._bounded(stream, self.power)
                cols = self.power.setdefault(stream, [0, 0])
                cols[1 if (power_is_late(payload) if late is None else late) else 0] += 1
                if env.seq is not None:
                    seqs = self.power_seqs.get(stream)
                    if seqs is None:
                        seqs = self.power_seqs[stream] = SeqRanges()
                    seqs.add(env.seq)
        elif kind == "status" and env.schema == "mntes.status" and not env.problem:
            service = self.status(payload)
            if service is not None and (topic in self.status_topics or len(self.status_topics) < _MAX_CONVERTERS):
                self.status_topics[topic] = service
        return None

    def _counts(self, topic: str, env: Envelope, t_ns: int, source: str | None = None) -> Verdict | None:
        stream = self._stream_of.get(topic)
        if stream is None:
            stream = self._stream(topic)
            if stream is None:
                return None
            stream = self._bounded(stream, self.ledger.streams)
            if len(self._stream_of) < _MAX_STREAMS:
                self._stream_of[topic] = stream
        self.ledger.received(stream)
        if env.problem or env.seq is None:
            self.ledger.rejected(stream, "malformed" if env.problem else "no_seq")
            return None
        seq = self.sequences.get(topic)
        if seq is None:
            seq = PublisherSequences()
            if len(self.sequences) < _MAX_STREAMS:
                self.sequences[topic] = seq
        verdict = seq.observe(env.seq, env.publish_time_ns if env.publish_time_ns is not None else t_ns, source)
        if verdict is Verdict.DUPLICATE:
            self.ledger.duplicate(stream)
            return verdict
        self.ledger.done(stream)
        seqs = self.counts_seqs.get(stream)
        if seqs is None:
            seqs = self.counts_seqs[stream] = SeqRanges()
        seqs.add(env.seq)
        if verdict is Verdict.RESET:
            self.restarted.add(stream)
        return verdict

    def unpowered(self, open_only: bool = False) -> dict[str, dict]:
        """Per stream, the counts chunks recorded without their power: ``count``, ``ranges`` (``[lo, hi)``),
        ``untracked`` (numbers the bounded ranges could not place: the count is then a bound), ``restarted``.

        ``open_only``: only the numbers below the newest power recorded of the stream (a hole while power flows
        after it), streams without any power left out (no converter yet: ``Coverage.unconverted`` says those);
        else every counts chunk without power, the tail included (what the recording lacks now).
        """
        return unpowered(self.counts_seqs, self.power_seqs, self.restarted, open_only)

    def status(self, payload: bytes) -> str | None:
        """A converter's status message: keep the newest of each service (its ledger and counters).

        Returns the service it names, or None for a status that does not decode (or one too many services)."""
        from mntes_stream.io.messages import StatusMessage

        try:
            st = StatusMessage.from_bytes(payload)
        except MntesError:
            return None
        old = self.converters.get(st.service)
        if old is None and len(self.converters) >= _MAX_CONVERTERS:
            return None
        if old is None or old["t_ns"] <= st.t_ns:
            entry = {name: int(getattr(st, name, 0) or 0) for name in _STATUS_FIELDS}
            entry["ledger"] = dict(getattr(st, "ledger", None) or {})
            self.converters[st.service] = entry
        return st.service

    def converter_line(self, service: str) -> str:
        """A converter's ledger in one line, as its newest recorded status says."""
        return _converter_line(self.converters[service])

    def ledger_now(self) -> Ledger:
        """The recorder's ledger, each stream's never-received count as its tracker says now."""
        missing: dict[str, int] = {}
        for topic, seq in self.sequences.items():
            stream = self._stream_of.get(topic, OTHER)
            missing[stream] = missing.get(stream, 0) + seq.lost
        for stream, n in missing.items():
            self.ledger.set_missing(stream, n)
        return self.ledger

    def conflicts(self) -> dict[str, int]:
        """Streams two or more publishers send side by side -> how many (``core.sequence.PublisherSequences``)."""
        return {self._stream_of.get(t, OTHER): s.publishers for t, s in self.sequences.items() if s.conflict}

    def seqs_dict(self) -> dict[str, dict]:
        """Per stream, the ranges of the counts and power numbers recorded (JSON-ready; :func:`seqs_from_dict`)."""
        out = {}
        for stream in sorted(set(self.counts_seqs) | set(self.power_seqs), key=stream_order):
            c, p = self.counts_seqs.get(stream, SeqRanges()), self.power_seqs.get(stream, SeqRanges())
            d = {"counts": c.to_list(), "power": p.to_list()}
            if c.untracked or p.untracked:
                d["untracked"] = [c.untracked, p.untracked]
            if stream in self.restarted:
                d["restarted"] = True
            out[stream] = d
        return out

    def metadata(self, run: str, file_seq: int) -> dict[str, str]:
        """The ``mntes.ledger`` record of this run up to and including file ``file_seq``."""
        led = self.ledger_now()
        out = {
            "lost_means": LOST_MEANS,
            "scope": "the recorder's run up to and including this file (run, file_seq)",
            "run": str(run),
            "file_seq": str(int(file_seq)),
            "recorder": json.dumps(led.as_dict(), separators=(",", ":")),
            "recorder_line": led.line(),
            "power": json.dumps(self.power, separators=(",", ":")),
            "converters": json.dumps(self.converters, separators=(",", ":")),
            "seqs": json.dumps(self.seqs_dict(), separators=(",", ":")),
            "conflicts": json.dumps(self.conflicts(), separators=(",", ":")),
        }
        for name, entry in sorted(self.converters.items()):
            out[f"converter.{name}"] = _converter_line(entry)
        return out


def unpowered(counts_seqs: dict, power_seqs: dict, restarted=(), open_only: bool = False) -> dict[str, dict]:
    """Counts without power per stream, from the ranges of numbers recorded (see :meth:`RecordingBook.unpowered`)."""
    out = {}
    empty = SeqRanges()
    for stream, c in counts_seqs.items():
        p = power_seqs.get(stream, empty)
        if open_only and p.newest is None:
            continue
        holes = c.minus(p, below=p.newest if open_only else None)
        untracked = c.untracked + p.untracked
        if holes or untracked:
            d = {"count": sum(hi - lo for lo, hi in holes), "ranges": [[lo, hi] for lo, hi in holes]}
            if untracked:
                d["untracked"] = untracked
            if stream in restarted:
                d["restarted"] = True
            out[stream] = d
    return dict(sorted(out.items(), key=lambda kv: stream_order(kv[0])))


def seqs_from_dict(d: dict) -> tuple[dict, dict, set]:
    """The counts and power ranges per stream (and the restarted streams) of :meth:`RecordingBook.seqs_dict`."""
    counts, power, restarted = {}, {}, set()
    for stream, v in (d or {}).items():
        cu, pu = (v.get("untracked") or [0, 0])[:2]
        counts[stream] = SeqRanges.from_list(v.get("counts") or (), cu)
        power[stream] = SeqRanges.from_list(v.get("power") or (), pu)
        if v.get("restarted"):
            restarted.add(stream)
    return counts, power, restarted


def unpowered_line(holes: dict, most_streams: int = 8) -> str:
    """What a recording lacks, in one clause: the counts chunks without power per stream, their numbers, and that
    offline ``convert`` gives their power ("" when there are none)."""
    if not holes:
        return ""
    total = sum(h["count"] for h in holes.values())
    parts = []
    for stream, h in list(holes.items())[:most_streams]:
        parts.append(f"{stream} {format_ranges(h['ranges'], 4)}{_notes(h)}" if h["ranges"] else f"{stream}{_notes(h)}")
    more = len(holes) - most_streams
    return (f"{total} counts chunk(s) recorded without power ({'; '.join(parts)}"
            f"{f'; and {more} more stream(s)' if more > 0 else ''}): offline `mntes-stream convert` of this "
            "recording gives their power")


def conflict_line(conflicts: dict, most: int = 8) -> str:
    """Streams two or more publishers sent side by side, in one clause ("" when none)."""
    if not conflicts:
        return ""
    items = sorted(conflicts.items(), key=lambda kv: stream_order(kv[0]))
    names = ", ".join(f"{s} by {n}" for s, n in items[:most]) + (", ..." if len(items) > most else "")
    return (f"{len(items)} counts stream(s) sent by more than one publisher side by side ({names}): two sources or "
            "bridges on one setup? Each one's chunks are numbered apart, a chunk two send is a duplicate")


def _notes(h: dict) -> str:
    """What makes a stream's counts without power a bound rather than exact (see :func:`unpowered`)."""
    return "".join([f" (+ up to {h['untracked']} not placed: too fragmented)" if h.get("untracked") else "",
                    " (its numbering restarted: before and after are merged)" if h.get("restarted") else ""])


def _converter_line(c: dict) -> str:
    led = c.get("ledger") or {}
    if led:
        return Ledger.from_dict(led).line()
    return (f"converted {c.get('chunks_converted', 0)}, shed {c.get('chunks_shed', 0)}, lost {c.get('chunks_lost', 0)} "
            "(its status has no per-stream ledger)")


@dataclass(frozen=True)
class RecordingLedger:
    """The ledger of a recording, as :func:`recording_ledger` found it.

    ``source`` is ``metadata`` (the recorder's ``mntes.ledger`` at close) or
    ``recomputed`` (from the recorded messages; ``note`` says why);
    ``unpowered`` the counts chunks recorded without power, per stream (:func:`unpowered`; None: the metadata of
    an earlier recorder, which kept no numbers); ``conflicts`` the streams the recorder saw sent by more than
    one publisher side by side (a file's messages do not name their publisher: recomputed, none is found);
    ``recorder`` the counts streams (verb ``recorded``); ``power`` per stream
    ``[live, late]`` power chunks recorded; ``converters`` each converter's
    newest recorded status (``ledger`` as a dict, and its counters).
    """

    source: str
    recorder: Ledger
    power: dict
    converters: dict
    note: str = ""
    runs: int = 1
    lost_means: str = LOST_MEANS
    unpowered: dict | None = None
    conflicts: dict | None = None

    def as_dict(self) -> dict:
        return {"source": self.source, "note": self.note, "runs": self.runs, "lost_means": self.lost_means,
                "recorder": self.recorder.as_dict(), "recorder_line": self.recorder.line(), "power": self.power,
                "converters": self.converters, "unpowered": self.unpowered, "conflicts": self.conflicts,
                "converter_lines": {n: Ledger.from_dict(c.get("ledger") or {}).line() for n, c in self.converters.items()}}

    def lines(self) -> list[str]:
        """The ledger as text lines: totals, each converter's, then one row per stream."""
        how = "mntes.ledger metadata" if self.source == "metadata" else f"recomputed from the messages ({self.note})"
        out = [f"ledger ({how}):", f"  recorder: counts {self.recorder.line()}"]
        for name, c in sorted(self.converters.items()):
            line = _converter_line(c)
            held = f"; set aside now {c['chunks_set_aside']}" if c.get("chunks_set_aside") else ""
            out.append(f"  converter {name} (last recorded status): {line}{held}")
        live, late = (sum(v[i] for v in self.power.values()) for i in (0, 1))
        out.append(f"  power recorded: live {live}" + (f", late {late}" if late else ""))
        conv = {}
        for c in self.converters.values():
            conv = _merge_dicts(conv, c.get("ledger") or {})
        streams = sorted(set(self.recorder.streams) | set(self.power) | set(conv), key=stream_order)
        if streams:
            out.append(f"  {'stream':<12}{'recorded':>10}{'never rcvd':>11}{'dup':>6}{'power':>8}{'late':>6}"
                       f"{'conv shed':>10}{'conv rej':>9}")
        for s in streams:
            r = self.recorder.streams.get(s)
            p = self.power.get(s, [0, 0])
            c = Ledger.from_dict({s: conv[s]}).streams[s] if s in conv else None
            out.append(f"  {s:<12}{r.done if r else 0:>10}{r.missing if r else 0:>11}{r.duplicate if r else 0:>6}"
                       f"{p[0]:>8}{p[1]:>6}{c.shed_total if c else 0:>10}{c.rejected_total if c else 0:>9}")
        if self.unpowered is None:
            out.append("  counts without power: unknown (ledger metadata of an earlier recorder, without numbers)")
        elif self.unpowered:
            out.append(f"  counts without power: {sum(h['count'] for h in self.unpowered.values())} chunk(s) never "
                       "converted in this recording; offline `mntes-stream convert` of it gives their power:")
            for s, h in self.unpowered.items():
                out.append(f"    {s}: {h['count']} chunk(s), {format_ranges(h['ranges'], 16)}{_notes(h)}")
        else:
            out.append("  counts without power: none (every recorded counts chunk has its power)")
        if self.conflicts:
            out.append(f"  CONFLICT: {conflict_line(self.conflicts)}")
        out.append(f"  ({self.lost_means})")
        return out


def _merge_dicts(a: dict, b: dict) -> dict:
    led = Ledger.from_dict(a)
    led.merge(Ledger.from_dict(b))
    return led.as_dict()


def recording_ledger(session) -> RecordingLedger:
    """The ledger of a recording (an ``io.mcap.Session``): its ``mntes.ledger`` metadata when every file has one
    (the last file of each recorder run counts), else recomputed from the recorded messages."""
    records = [m for m in session.metadata() if m.name == LEDGER_METADATA]
    with_ledger = {m.path for m in records}
    missing = [f.path for f in session.files if f.path not in with_ledger]
    if records and not missing:
        try:
            return _from_metadata(records)
        except (ValueError, TypeError, KeyError) as exc:
            note = f"its {LEDGER_METADATA} metadata is unreadable: {exc}"
    else:
        note = (f"{len(missing)} of {len(session.files)} file(s) without {LEDGER_METADATA} metadata: "
                "not finished by the recorder" if session.files else "no files")
    return recompute_ledger(session, note)


def recompute_ledger(session, note: str = "") -> RecordingLedger:
    """The ledger of a recording from its messages alone (counts, power, status), as the recorder would book them."""
    # One setup (the usual case): streams named "<board>/<module>" as the recorder names them.
    setups = {t.split("/")[1] for t in session.message_counts() if keys.kind_of(t) == "counts"}
    book = RecordingBook(setups.pop() if len(setups) == 1 else None)
    try:
        for m in session.iter_messages():
            if keys.kind_of(m.topic) in ("counts", "power", "status"):
                book.add(m.topic, m.payload, peek_envelope(m.payload), m.log_time_ns)
    except MntesError as exc:  # what was read so far is still booked; the rest is said
        note = f"{note}; reading stopped: {exc}" if note else f"reading stopped: {exc}"
    return RecordingLedger("recomputed", book.ledger_now(), book.power, book.converters, note=note,
                           unpowered=book.unpowered())


def _from_metadata(records) -> RecordingLedger:
    last: dict[str, dict] = {}
    for m in records:
        d = m.data
        run = d.get("run", m.path)
        if run not in last or int(d.get("file_seq", 0)) >= int(last[run].get("file_seq", 0)):
            last[run] = d
    recorder = Ledger("recorded")
    power: dict[str, list[int]] = {}
    converters: dict[str, dict] = {}
    counts, pw, restarted, conflicts = {}, {}, set(), {}
    numbered = all("seqs" in d for d in last.values())
    for d in last.values():
        recorder.merge(Ledger.from_dict(json.loads(d["recorder"]), "recorded"))
        for s, (live, late) in json.loads(d.get("power") or "{}").items():
            cols = power.setdefault(s, [0, 0])
            cols[0] += int(live)
            cols[1] += int(late)
        for name, c in json.loads(d.get("converters") or "{}").items():
            if name not in converters or int(c.get("t_ns", 0)) > int(converters[name].get("t_ns", 0)):
                converters[name] = c
        if numbered:  # runs of recorders (restarted, or shards): a chunk with its power in any run has it
            c_run, p_run, r_run = seqs_from_dict(json.loads(d["seqs"]))
            for mine, theirs in ((counts, c_run), (pw, p_run)):
                for s, r in theirs.items():
                    mine[s] = mine[s].union(r) if s in mine else r
            restarted |= r_run
        for s, n in json.loads(d.get("conflicts") or "{}").items():
            conflicts[s] = max(conflicts.get(s, 0), int(n))
    lost_means = next(iter(last.values())).get("lost_means", LOST_MEANS)
    return RecordingLedger("metadata", recorder, power, converters, runs=len(last), lost_means=lost_means,
                           unpowered=unpowered(counts, pw, restarted) if numbered else None, conflicts=conflicts)


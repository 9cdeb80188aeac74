"""A recording rewritten with Foxglove-readable json channels beside its msgpack originals.

``mntes-stream transcode IN OUT --foxglove``: every recorded message is copied
verbatim (same topic, schema, log time; the writer re-derives publish time
and sequence from the payload exactly as the recorder did), with the
recording's own metadata and attachments; the file starts with the flag and
unit records of :mod:`mntes_stream.io.describe`; json channels already in
the input are left out (made anew). With ``foxglove``, each
power, housekeeping and status message also yields the json messages of
:class:`~mntes_stream.foxglove.translate.FoxgloveView` (encoding ``json``,
schema encoding ``jsonschema``). No foxglove-sdk is needed: the MCAP writer
is the recorder's.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

from mntes_stream.errors import SchemaError

__all__ = ["TranscodeStats", "transcode", "JsonChannels"]

_TRANSLATED = ("mntes.power", "mntes.hk", "mntes.status")


class JsonChannels:
    """Adds the Foxglove json channels of each recorded message to an MCAP writer (recorder and transcoder).

    Parameters
    ----------
    writer : McapFileWriter or RotatingMcapWriter
    view : FoxgloveView, optional
    """

    def __init__(self, writer, view=None):
        from mntes_stream.foxglove.translate import SCHEMAS, FoxgloveView

        self.writer, self.view, self._schemas = writer, view or FoxgloveView(), SCHEMAS
        self.messages = 0
        self.bad = 0

    def add(self, schema_name: str, payload: bytes) -> None:
        """Translate one payload that claimed ``schema_name`` (others, and bad payloads, add nothing)."""
        if schema_name not in _TRANSLATED:
            return
        from mntes_stream.io.messages import decode

        try:
            msg = decode(payload, _TRANSLATED)
        except SchemaError:
            self.bad += 1  # recorded as it came; nothing to show
            return
        for out in self.view.translate(msg):
            self.writer.write_json(out.topic, out.schema, self._schemas[out.schema], out.message, out.log_time_ns)
            self.messages += 1


@dataclass(frozen=True)
class TranscodeStats:
    messages: int
    json_messages: int
    undecodable: int
    metadata: int
    attachments: int
    seconds: float
    damaged: str = ""  # what of the input could not be read (marked in the output's mntes.damaged metadata)


def transcode(source, out: str | Path, *, foxglove: bool = True, view=None, compression: str = "zstd") -> TranscodeStats:
    """Rewrite a recording (a file, a directory of rotated files, or a list) into one MCAP file ``out``.

    Parameters
    ----------
    source
        Anything :class:`mntes_stream.io.mcap.Session` reads.
    out : path
        Created; an existing file is an error.
    foxglove : bool
        Add the json channels.
    view : FoxgloveView, optional
        Which detectors and how many samples (default: :class:`FoxgloveView` defaults).
    """
    from mntes_stream.io.describe import FLAGS_METADATA, UNITS_METADATA
    from mntes_stream.io.mcap import PROVENANCE_ATTACHMENT, PROVENANCE_SCHEMA, McapFileWriter, Session
    from mntes_stream.io.mcap.envelope import writer_description

    t0 = time.monotonic()
    session = Session(source)
    # Provenance records and attachments are re-made by the writer from the provenance messages.
    regenerated = {PROVENANCE_SCHEMA, FLAGS_METADATA, UNITS_METADATA}
    metadata = [m for m in session.metadata() if m.name not in regenerated]
    attachments = [a for a in session.attachments() if a.name != PROVENANCE_ATTACHMENT]
    first = {}
    for m in metadata:  # one record per name fits the writer's start; the rest are added after
        first.setdefault(m.name, m.data)
    first["mntes.transcode"] = writer_description(source=", ".join(str(p) for p in session.files),
                                                  foxglove_channels=str(bool(foxglove)))
    n = 0
    with McapFileWriter(out, compression=compression, metadata=first, whole=True) as writer:  # OUT only when finished
        seen = set()
        for m in metadata:
            if m.name in seen:
                writer.add_metadata(m.name, m.data)
            seen.add(m.name)
        for a in attachments:
            writer.add_attachment(a.name, a.media_type, a.data, a.log_time_ns, a.create_time_ns)
        channels = JsonChannels(writer, view) if foxglove else None
        # json channels already in the input (topics "/...", never a zenoh key) are made anew, not copied.
        for msg in session.iter_messages([t for t in session.message_counts() if not t.startswith("/")]):
            writer.write(msg.topic, msg.payload, msg.log_time_ns)
            n += 1
            if channels is not None:
                channels.add(msg.schema_name, msg.payload)
        json_messages = writer.json_messages
        if session.damage_line():
            from mntes_stream.io.mcap.repair import DAMAGE_METADATA, damage_metadata

            writer.add_metadata(DAMAGE_METADATA, damage_metadata(session.damage, session.unlabelled_messages))
    return TranscodeStats(messages=n, json_messages=json_messages, undecodable=channels.bad if channels else 0,
                          metadata=len(metadata), attachments=len(attachments), seconds=time.monotonic() - t0,
                          damaged=session.damage_line())

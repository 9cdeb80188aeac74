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

from mntes_stream.io.mcap.envelope import (
    MESSAGE_ENCODING,
    PROVENANCE_ATTACHMENT,
    PROVENANCE_SCHEMA,
    RECORDING_METADATA,
    Envelope,
    peek_envelope,
    writer_description,
)
from mntes_stream.io.mcap.recovery import FileInfo, TruncatedFileWarning
from mntes_stream.io.mcap.rotating import RotatingMcapWriter
from mntes_stream.io.mcap.session import (
    RecordedAttachment,
    RecordedMessage,
    RecordedMetadata,
    Session,
    SessionsWarning,
    iter_messages,
    latest_provenance,
    read_attachments,
    read_metadata,
    session_files,
    topic_matcher,
)
from mntes_stream.io.mcap.writer import McapFileWriter

__all__ = [
    "MESSAGE_ENCODING",
    "PROVENANCE_ATTACHMENT",
    "PROVENANCE_SCHEMA",
    "RECORDING_METADATA",
    "Envelope",
    "FileInfo",
    "McapFileWriter",
    "RecordedAttachment",
    "RecordedMessage",
    "RecordedMetadata",
    "RotatingMcapWriter",
    "Session",
    "SessionsWarning",
    "TruncatedFileWarning",
    "iter_messages",
    "latest_provenance",
    "peek_envelope",
    "read_attachments",
    "read_metadata",
    "session_files",
    "topic_matcher",
    "writer_description",
]

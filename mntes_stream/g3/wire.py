"""G3 frames on the wire: a bounded frame splitter in front of spt3g, and whole-or-nothing G3 files.

spt3g's ``G3Reader`` trusts every length a byte stream claims: a blob length
of 2**63 raises MemoryError, one of 2 GB is really allocated, and a
big-endian flag or an unknown version kills the reader. So the bridge and
the file readers split the stream into frames here first, checking each
claim against a budget (``max_frame_bytes``) before a byte of it is kept,
and hand spt3g only a complete frame whose layout is sound.

A frame, as spt3g writes it (cereal's portable binary archive, the same on
disk and from ``G3NetworkSender``)::

    u8 endianness flag (1: little endian)   u32 version (1)   u32 entries   u32 frame type
    entries x (u64 name length, name, u64 blob length, blob)
    u32 CRC

Memory is bounded by the budget: bytes are buffered only as they arrive,
and a frame whose claims exceed it is refused at its header. The CRC
(CRC-32C without inversion over each entry's name and blob) is spt3g's to
check. What is not bounded here: lengths *inside* a blob (a vector's
element count), which spt3g decodes when an entry is read. A claim beyond
memory fails at once (counted ``undecodable``); one that fits in memory is
allocated before the read fails, so a sender that computes the CRC can
still make the bridge allocate (not keep) that much: run it under a memory
limit where the sender is not trusted.
"""

from __future__ import annotations

import bz2
import gzip
import os
import struct
from pathlib import Path

from mntes_stream.errors import ConfigError, SchemaError

__all__ = ["BadFrame", "FrameSplitter", "decode_frame", "encode_frame", "iter_file_frames", "AtomicG3Writer",
           "FRAME_REASONS", "STREAM_REASONS"]

FRAME_VERSION = 1
_HEADER = struct.Struct("<BIII")
_U64 = struct.Struct("<Q")
MAX_ENTRIES = 1 << 16       # a DAQ frame has tens; the bound keeps a header walk short
MAX_NAME_BYTES = 1 << 12

# A stream that breaks one of these has lost its framing: the rest of the connection (or file) is unreadable.
STREAM_REASONS = ("big_endian", "bad_header", "frame_version", "too_many_entries", "name_too_long",
                  "frame_too_large", "truncated")
# A frame with one of these is skipped; the stream goes on.
FRAME_REASONS = ("crc", "undecodable", "wrong_type", "empty_map", "before_wiring", "out_of_order", "bad_content")


class BadFrame(SchemaError):
    """A G3 frame (or the stream around it) that cannot be used; ``reason`` is its counter's name."""

    def __init__(self, message: str, reason: str):
        super().__init__(message)
        self.reason = reason  # the G3 reasons above, not the message schema's


class FrameSplitter:
    """Complete frames (their bytes) out of a byte stream, every length claim checked first.

    Parameters
    ----------
    max_frame_bytes : int
        The largest frame accepted; a header claiming more raises :class:`BadFrame`
        (``frame_too_large``) before anything beyond the header is kept.
    """

    def __init__(self, max_frame_bytes: int):
        if max_frame_bytes < _HEADER.size + 4:
            raise ConfigError(f"max_frame_bytes must be at least {_HEADER.size + 4}")
        self.max_frame_bytes = int(max_frame_bytes)
        self._buf = bytearray()
        self._off = 0           # start of the current frame in _buf
        self._pos = 0           # header walk position, relative to _off
        self._left: int | None = None  # entries still to walk (None: fixed header not read yet)
        self.offset = 0         # stream offset of the current frame (for messages)

    def pending(self) -> int:
        """Bytes received and not yet returned as a frame."""
        return len(self._buf) - self._off

    def feed(self, data) -> None:
        if self._off and (self._off >= len(self._buf) // 2):
            del self._buf[:self._off]  # compact rarely: per frame would move the whole buffer each time
            self._off = 0
        self._buf += data

    def _bad(self, text: str, reason: str) -> BadFrame:
        return BadFrame(f"G3 frame at byte {self.offset}: {text}", reason)

    def next(self) -> bytes | None:
        """The next complete frame, or None until more bytes arrive (BadFrame if the stream is not G3)."""
        buf, off = self._buf, self._off
        avail = len(buf) - off
        if self._left is None:
            if avail < _HEADER.size:
                return None
            endian, version, n, _ = _HEADER.unpack_from(buf, off)
            if endian != 1:
                raise self._bad("big-endian frame (spt3g writes little endian)" if endian == 0
                                else f"endianness flag {endian}: not a G3 frame",
                                "big_endian" if endian == 0 else "bad_header")
            if version != FRAME_VERSION:
                raise self._bad(f"frame version {version} (known: {FRAME_VERSION})", "frame_version")
            if n > MAX_ENTRIES:
                raise self._bad(f"{n} entries claimed (at most {MAX_ENTRIES})", "too_many_entries")
            self._left, self._pos = n, _HEADER.size
        while self._left:
            pos = self._pos
            if avail < pos + 8:
                return None
            (n_name,) = _U64.unpack_from(buf, off + pos)
            if n_name > MAX_NAME_BYTES:
                raise self._bad(f"entry name of {n_name} bytes claimed (at most {MAX_NAME_BYTES})", "name_too_long")
            if avail < pos + 16 + n_name:
                return None
            (n_blob,) = _U64.unpack_from(buf, off + pos + 8 + n_name)
            end = pos + 16 + n_name + n_blob
            if end + 4 > self.max_frame_bytes:
                raise self._bad(f"blob of {n_blob} bytes claimed: frame over the budget of {self.max_frame_bytes} "
                                "bytes (max_frame_mb)", "frame_too_large")
            self._pos, self._left = end, self._left - 1  # the blob's bytes may not be here yet: walked over
        end = self._pos + 4
        if avail < end:
            return None
        frame = bytes(buf[off:off + end])
        self._off += end
        self.offset += end
        self._left, self._pos = None, 0
        return frame


def _loader(core):
    # spt3g 1.0.2 (pybind11) fills a frame with _cereal_loads; so3g's bundled copy (boost.python) with
    # __setstate__ on a new frame (1.0.2's __setstate__ wants an unconstructed instance).
    if hasattr(core.G3Frame, "_cereal_loads"):
        def load(data: bytes):
            f = core.G3Frame()
            f._cereal_loads(data)
            return f
    else:
        def load(data: bytes):
            f = core.G3Frame()
            f.__setstate__(({}, data))
            return f
    return load


def decode_frame(data: bytes):
    """A G3Frame from the bytes of one frame (as :class:`FrameSplitter` gives them); BadFrame if it is not one.

    The entries stay serialized until read (spt3g decodes lazily): a bad blob
    shows when the translator reads it.
    """
    from mntes_stream.g3.runtime import spt3g

    core, _ = spt3g()
    try:
        return _loader(core)(data)
    except (RuntimeError, MemoryError, ValueError) as exc:
        text = str(exc).split(" (in ", 1)[0]
        raise BadFrame(f"G3 frame not decodable: {text}", "crc" if "CRC" in text else "undecodable") from None


def encode_frame(frame) -> bytes:
    """The bytes spt3g writes for ``frame`` (its own serialization)."""
    return bytes(frame.__getstate__()[1])


def _open_read(path: Path):
    name = path.name.lower()
    if name.endswith(".gz"):
        return gzip.open(path, "rb")
    if name.endswith(".bz2"):
        return bz2.open(path, "rb")
    if name.endswith(".zst"):
        from mntes_stream.errors import import_extra

        zstd = import_extra("zstandard", "g3")
        return zstd.ZstdDecompressor().stream_reader(open(path, "rb"), closefd=True)
    return open(path, "rb")


def iter_file_frames(path, max_frame_bytes: int, bad: dict | None = None, read_bytes: int = 1 << 20):
    """Frames of one G3 file (any of spt3g's compressions), every length claim bounded.

    A frame that is not decodable is counted in ``bad`` (reason -> count) and
    skipped; a stream that loses its framing (a claim over the budget, a
    truncated tail) is counted and ends the file. A file whose first frame is
    not G3 raises ConfigError.
    """
    path = Path(path)
    bad = {} if bad is None else bad
    split = FrameSplitter(max_frame_bytes)
    n = 0
    try:
        with _open_read(path) as f:
            while True:
                data = f.read(read_bytes)
                if data:
                    split.feed(data)
                while True:
                    try:
                        raw = split.next()
                    except BadFrame as exc:
                        if not n:
                            raise ConfigError(f"{path}: not a readable G3 file ({exc})") from None
                        bad[exc.reason] = bad.get(exc.reason, 0) + 1
                        return
                    if raw is None:
                        break
                    n += 1
                    try:
                        yield decode_frame(raw)
                    except BadFrame as exc:
                        bad[exc.reason] = bad.get(exc.reason, 0) + 1
                if not data:
                    break
    except (OSError, EOFError, ValueError) as exc:  # a damaged gzip/bz2/zstd stream
        if not n:
            raise ConfigError(f"{path}: not a readable G3 file ({exc})") from None
        bad["truncated"] = bad.get("truncated", 0) + 1
        return
    if split.pending():
        if not n:
            raise ConfigError(f"{path}: not a readable G3 file (no complete frame)")
        bad["truncated"] = bad.get("truncated", 0) + 1


class AtomicG3Writer:
    """A G3 file that appears under its name only when complete.

    Frames go to ``<path>.partial`` (compressed as the name says: ``.gz``,
    ``.bz2``, ``.zst``); :meth:`close` flushes, syncs and renames. Leaving the
    ``with`` block on an exception removes the partial file, and a failed
    write (a full disk) is a one-line :class:`ConfigError`: at once, or, with
    ``defer_errors`` (the writer as a G3Pipeline module, where spt3g would log
    an exception as a warning of its own), from :meth:`close`; :attr:`error`
    says so meanwhile and later frames are ignored.
    """

    def __init__(self, path, defer_errors: bool = False):
        self.path = Path(path)
        self.defer_errors = defer_errors
        self.error: str | None = None
        if self.path.exists():
            raise ConfigError(f"{self.path} exists: not overwritten")
        self.tmp = self.path.with_name(self.path.name + ".partial")
        self.frames = 0
        self._raw = None
        self._f = None
        try:
            self._raw = open(self.tmp, "wb")
            name = self.path.name.lower()
            if name.endswith(".gz"):
                self._f = gzip.GzipFile(fileobj=self._raw, mode="wb")
            elif name.endswith(".bz2"):
                self._f = bz2.BZ2File(self._raw, "wb")
            elif name.endswith(".zst"):
                from mntes_stream.errors import import_extra

                self._f = import_extra("zstandard", "g3").ZstdCompressor().stream_writer(self._raw, closefd=False)
            else:
                self._f = self._raw
        except OSError as exc:
            self.abort()
            raise ConfigError(f"{self.path}: cannot write ({exc.strerror or exc})") from None

    def __call__(self, frame) -> None:
        """Write one frame (usable as the last module of a G3Pipeline; EndProcessing is not written,
        as spt3g's G3Writer does not)."""
        if self.error is not None or str(frame.type) == "EndProcessing":
            return
        try:
            self._f.write(encode_frame(frame))
        except OSError as exc:
            self.abort()
            self.error = f"{self.path}: write failed after {self.frames} frames ({exc.strerror or exc}); nothing written"
            if not self.defer_errors:
                raise ConfigError(self.error) from None
            return
        self.frames += 1

    def close(self) -> None:
        if self.error is not None:
            raise ConfigError(self.error)
        try:
            if self._f is not self._raw:
                self._f.close()
            self._raw.flush()
            os.fsync(self._raw.fileno())
            self._raw.close()
            os.replace(self.tmp, self.path)
        except OSError as exc:
            self.abort()
            raise ConfigError(f"{self.path}: write failed at close ({exc.strerror or exc}); nothing written") from None

    def abort(self) -> None:
        """Drop the partial file."""
        for f in (self._f, self._raw):
            if f is not None:
                try:
                    f.close()
                except (OSError, ValueError):
                    pass
        self._f = self._raw = None
        try:
            self.tmp.unlink()
        except FileNotFoundError:
            pass

    def __enter__(self):
        return self

    def __exit__(self, exc_type, exc, tb):
        if exc_type is None:
            self.close()
        else:
            self.abort()

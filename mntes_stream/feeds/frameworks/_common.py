"""What every framework adapter shares: segments, sample rate, focal plane, metadata, directory output (numpy only)."""

from __future__ import annotations

import json
import shutil
import time
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mntes_stream import __version__
from mntes_stream.core import flags as fl
from mntes_stream.errors import ConfigError
from mntes_stream.feeds.blocks import GAP_FACTOR, TodBlock, concat_blocks

__all__ = ["FocalPlane", "Positions", "as_block", "segments", "sample_rate_hz", "focal_plane", "read_positions", "metadata",
           "observation_blocks", "PLACEHOLDER_NOTE", "output_dir", "check_room"]

PLACEHOLDER_NOTE = ("placeholder: no detector positions or polarisation angles are known to mntes-stream for these "
                    "detectors; every detector is put at the boresight (xi = eta = 0) with polarisation angle 0")


@dataclass(frozen=True)
class FocalPlane:
    """Detector positions for the frameworks' focal planes.

    Attributes
    ----------
    xi_rad, eta_rad, gamma_rad : ndarray of float64, shape (n_det,)
        Position on the sky relative to the boresight (xi, eta) and polarisation
        angle (gamma), radians, in the xi/eta/gamma convention shared by TOAST
        (``instrument_coords.xieta_to_quat``) and sotodlib (``focal_plane``).
    placeholder : bool
        True when nothing was known and every detector sits at the boresight
        with gamma = 0 (:data:`PLACEHOLDER_NOTE`).
    """

    xi_rad: np.ndarray
    eta_rad: np.ndarray
    gamma_rad: np.ndarray
    placeholder: bool
    source: str = "given by the caller (positions=)"

    @property
    def note(self) -> str:
        return PLACEHOLDER_NOTE if self.placeholder else self.source


class Positions(dict):
    """``detector id -> (xi_rad, eta_rad, gamma_rad)`` that says where it came from (``source``)."""

    def __init__(self, data, source: str):
        super().__init__(data)
        self.source = source


def as_block(data) -> TodBlock:
    """A :class:`TodBlock`, or consecutive blocks of one stream (e.g. from a live feed) concatenated."""
    if isinstance(data, TodBlock):
        return data
    blocks = list(data)
    if not blocks or not all(isinstance(b, TodBlock) for b in blocks):
        raise ConfigError("expected a TodBlock or a non-empty list of TodBlocks of one stream")
    return concat_blocks(blocks)


def _breaks(t_ns: np.ndarray) -> np.ndarray:
    """Indices where a new evenly sampled segment starts (a step outside 0.5..1.5 median periods)."""
    if t_ns.size < 3:
        return np.flatnonzero(np.diff(t_ns) <= 0) + 1
    step = np.diff(t_ns)
    period = float(np.median(step))
    # Gap fill keeps every step within a segment at most GAP_FACTOR periods; anything else is a break.
    return np.flatnonzero((step > GAP_FACTOR * period) | (step < (2 - GAP_FACTOR) * period)) + 1


def segments(data) -> list[TodBlock]:
    """The evenly sampled segments of a block (split at segment breaks: long pauses, clock steps).

    Parameters
    ----------
    data : TodBlock or list of TodBlock

    Returns
    -------
    list of TodBlock
        One block per segment, ``first_sample`` counting in the stream; one
        block when there is no break.
    """
    b = as_block(data)
    cuts = [0, *_breaks(b.t_ns).tolist(), b.n_samples]
    out = []
    for a, z in zip(cuts[:-1], cuts[1:]):
        out.append(TodBlock(b.setup, b.board, b.module, b.detectors, b.channels, b.t_ns[a:z], b.p_opt_w[:, a:z],
                            b.flags[:, a:z], b.first_sample + a, b.table_identities,
                            None if b.sigma_p_w is None else b.sigma_p_w[:, a:z]))
    return out


def single_segment(data) -> TodBlock:
    """The block, or ConfigError if it spans a segment break (frameworks need even sampling)."""
    b = as_block(data)
    if b.n_samples == 0:
        raise ConfigError(f"{b.name}: no samples")
    cuts = _breaks(b.t_ns)
    if cuts.size:
        raise ConfigError(f"{b.name}: {cuts.size} segment break(s) (first at sample {int(cuts[0])}); these frameworks "
                          "need even sampling: convert each of mntes_stream.feeds.frameworks.segments(block)")
    return b


def sample_rate_hz(block: TodBlock, given: float | None = None) -> float:
    """``given``, or the rate of the block's median sample step."""
    if given is not None:
        if not given > 0:
            raise ConfigError(f"sample_rate_hz must be > 0, got {given!r}")
        return float(given)
    if block.n_samples < 2:
        raise ConfigError(f"{block.name}: one sample gives no sample rate; pass sample_rate_hz")
    return 1e9 / float(np.median(np.diff(block.t_ns)))


def focal_plane(detectors: tuple, positions: Mapping | None = None) -> FocalPlane:
    """Positions of ``detectors`` from ``positions`` (id -> (xi_rad, eta_rad, gamma_rad)), or the placeholder.

    Raises
    ------
    ConfigError
        ``positions`` is given but misses a detector, or holds a non-finite value.
    """
    n = len(detectors)
    if positions is None:
        z = np.zeros(n)
        return FocalPlane(z, z.copy(), z.copy(), True)
    missing = [d for d in detectors if d not in positions]
    if missing:
        raise ConfigError(f"positions: no (xi, eta, gamma) for detector(s) {missing[:5]}")
    a = np.array([tuple(positions[d]) for d in detectors], dtype=np.float64).reshape(n, 3)
    if not np.isfinite(a).all():
        raise ConfigError("positions: xi, eta, gamma must be finite (radians)")
    source = getattr(positions, "source", None) or "given by the caller (positions=)"
    return FocalPlane(a[:, 0].copy(), a[:, 1].copy(), a[:, 2].copy(), False, source)


def read_positions(path) -> Positions:
    """Detector positions from a CSV file or a G3 file.

    CSV: a header ``detector,xi_rad,eta_rad,gamma_rad``, one row per detector.
    G3 (``.g3``, ``.g3.gz``, ...): the Wiring frame and the Calibration
    frame's ``BolometerProperties``
    (:func:`~mntes_stream.g3.focal_plane.positions_from_g3`).

    Returns
    -------
    Positions
        dict of str to (xi_rad, eta_rad, gamma_rad), with ``source`` saying where they came from.

    Raises
    ------
    ConfigError
        A missing column, a value that is not a finite number, or a detector given twice.
    """
    import csv

    from mntes_stream.g3.files import is_g3

    if is_g3(path):
        import sys

        from mntes_stream.g3.focal_plane import G3_NOTE, positions_from_g3

        if "so3g" in sys.modules:  # its bundled spt3g cannot read current G3: read on spt3g 1.0.2 in a child
            from mntes_stream.g3 import isolated

            got = isolated.run("positions", path=str(path))["positions"]
            return Positions({d: tuple(v) for d, v in got.items()}, f"{G3_NOTE}; file {path}")
        return Positions(positions_from_g3(path), f"{G3_NOTE}; file {path}")
    want = ["detector", "xi_rad", "eta_rad", "gamma_rad"]
    with open(path, newline="") as f:
        reader = csv.DictReader(f)
        if reader.fieldnames is None or [c.strip() for c in reader.fieldnames] != want:
            raise ConfigError(f"{path}: the header must be {','.join(want)}, got {reader.fieldnames}")
        out = {}
        for line, row in enumerate(reader, start=2):
            det = (row["detector"] or "").strip()
            try:
                vals = tuple(float(row[k]) for k in want[1:])
            except (TypeError, ValueError):
                raise ConfigError(f"{path}:{line}: xi_rad, eta_rad, gamma_rad must be numbers") from None
            if not det or not np.isfinite(vals).all():
                raise ConfigError(f"{path}:{line}: a detector id and finite angles (radians) are needed")
            if det in out:
                raise ConfigError(f"{path}:{line}: detector {det} given twice")
            out[det] = vals
    if not out:
        raise ConfigError(f"{path}: no detectors")
    return Positions(out, f"CSV file {path}")


def metadata(block: TodBlock, name: str, rate_hz: float, fp: FocalPlane, segment: int = 0, **extra) -> dict:
    """Provenance and conventions carried into every framework's object (JSON-able scalars and strings)."""
    return {
        "software_version": metadata_version(),
        "observation": name,
        "stream": block.name,
        "setup": block.setup,
        "board": int(block.board),
        "module": int(block.module),
        "segment": int(segment),
        "first_sample": int(block.first_sample),
        "t_start_ns": int(block.t_ns[0]) if block.n_samples else 0,
        "t_end_ns": int(block.t_ns[-1]) if block.n_samples else 0,
        "sample_rate_hz": float(rate_hz),
        "signal_units": "W",
        "signal_description": "optical power at the TES (MNTES); NaN where no usable power (see flags)",
        "flag_bits": json.dumps({n: b for b, n in fl.NAMES.items()}, sort_keys=True),
        "unusable_mask": int(fl.UNUSABLE),
        "table_identities": json.dumps(list(block.table_identities)),
        "focal_plane": fp.note,
        "focal_plane_placeholder": bool(fp.placeholder),
        **extra,
    }


def observation_blocks(source, *, room_in: Path | None = None,
                       **selection) -> Iterator[tuple[str, int, TodBlock, float | None]]:
    """A recording's observations: ``(name, segment, block, nominal rate)`` per module and segment.

    The name is the stream's (``<setup>_b<board>m<module>``), with ``_seg<k>``
    appended when a stream has several segments. ``source`` is what
    :class:`~mntes_stream.feeds.recorded.RecordedPower` takes, or one.
    ``room_in``: the partial output (file or directory); each observation is
    yielded only when its disk has room for it (:func:`check_room`).
    """
    from mntes_stream.feeds.recorded import RecordedPower

    rec = source if isinstance(source, RecordedPower) else RecordedPower(source, **selection)
    for sid, block in zip(rec.streams, rec.read().values()):
        if block.n_samples == 0:
            continue
        segs = segments(block)
        for k, seg in enumerate(segs):
            name = block.name if len(segs) == 1 else f"{block.name}_seg{k}"
            if room_in is not None:
                check_room(room_in, seg, name)
            yield name, k, seg, rec.streams[sid].sample_rate_hz


# Beyond an observation's own arrays: HDF5 metadata, the frameworks' extra fields.
_ROOM_MARGIN_BYTES = 1 << 20


def check_room(where: Path, block: TodBlock, name: str) -> None:
    """TransportError (one line) unless the disk of ``where`` has room for ``block`` written uncompressed.

    The frameworks write through h5py, and HDF5 2.0 meeting a full disk goes on
    after failed writes and crashes (rc 139), so the room is checked before
    each observation. The bound is generous (float64 power and flags, 25 %
    more, 256 bytes per sample for shared fields); a compressed output may
    fit where this refuses.
    """
    import os

    from mntes_stream.errors import TransportError

    where = Path(where)
    d = where if where.is_dir() else where.parent
    # Per sample, beside the detectors: TOAST's shared fields (times, flags, boresight quaternions,
    # position, velocity: about 130 bytes) and ours, doubled.
    need = int(1.25 * block.p_opt_w.nbytes) + block.flags.nbytes + 256 * block.n_samples + _ROOM_MARGIN_BYTES
    st = os.statvfs(d)
    free = st.f_bavail * st.f_frsize
    if free < need:
        out = where.name.removesuffix(".partial")
        raise TransportError(f"cannot write {out}: No space left on device ({free / 1e6:.1f} MB free in {d}, "
                             f"observation {name} may need up to {need / 1e6:.1f} MB)")


def observations(source, convert, **selection) -> list:
    """Every module-segment of a recording converted by ``convert(block, name=..., sample_rate_hz=...)``."""
    return [convert(b, name=name, sample_rate_hz=rate, segment=k)
            for name, k, b, rate in observation_blocks(source, **selection)]


class output_dir:
    """A directory written whole or not at all: files go to ``<out>.partial/``, renamed on success.

    An existing ``out`` is refused unless ``overwrite``; it is then replaced
    only if it holds nothing but ``.h5`` files (never a directory of other things).
    """

    def __init__(self, out, overwrite: bool):
        self.out = Path(out)
        self.tmp = self.out.with_name(self.out.name + ".partial")
        if self.out.exists():
            if not overwrite:
                raise ConfigError(f"{self.out} exists (use overwrite=True / --overwrite)")
            if not self.out.is_dir() or any(p.suffix != ".h5" or not p.is_file() for p in self.out.iterdir()):
                raise ConfigError(f"{self.out} is not a directory of .h5 files only; not replacing it")
        self.t_start = time.perf_counter()

    def __enter__(self) -> Path:
        shutil.rmtree(self.tmp, ignore_errors=True)
        self.tmp.mkdir(parents=True)
        return self.tmp

    def __exit__(self, exc_type, *exc) -> None:
        if exc_type is not None:
            shutil.rmtree(self.tmp, ignore_errors=True)
            return
        if self.out.exists():
            shutil.rmtree(self.out)
        self.tmp.replace(self.out)


def partial_file(out, overwrite: bool) -> tuple[Path, Path]:
    """``(out, out.partial)`` for a file written whole or not at all; ConfigError if ``out`` exists."""
    out = Path(out)
    if out.exists() and not overwrite:
        raise ConfigError(f"{out} exists (use overwrite=True / --overwrite)")
    tmp = out.with_name(out.name + ".partial")
    tmp.unlink(missing_ok=True)
    return out, tmp


def tree_bytes(path: Path) -> int:
    return path.stat().st_size if path.is_file() else sum(p.stat().st_size for p in path.rglob("*") if p.is_file())


def metadata_version() -> str:
    return f"mntes-stream {__version__}"


def summary(out, rec, names: list[str], samples: int, t_start: float):
    """The :class:`~mntes_stream.feeds.hdf5.ExportSummary` of a framework export (counts from ``rec.stats``)."""
    from mntes_stream.feeds.hdf5 import ExportSummary

    st = list(rec.stats.values())
    return ExportSummary(str(out), tuple(names), samples, sum(s.gap_samples for s in st),
                         sum(s.absent_samples for s in st), sum(s.duplicate_chunks for s in st),
                         sum(len(s.segment_starts) for s in st), tree_bytes(Path(out)), time.perf_counter() - t_start)

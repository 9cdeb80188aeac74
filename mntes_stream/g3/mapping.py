"""G3 frames -> the project's quantities: wiring both ways, housekeeping, bath temperature, counts.

Conventions (spt3g 1.0.2, read from its ``dfmux`` package):

- G3 time counts ticks of 10 ns since the Unix epoch: ``t_ns = ticks * 10``.
- The wiring map's ``module`` (0-7 on a board, across both mezzanines) and
  ``channel`` are 0-indexed; the housekeeping tree's mezzanine, module and
  channel are 1-indexed. spt3g's ``HousekeepingForBolo`` bridges them, and
  every housekeeping lookup here goes through it.
- A detector's id is ``core.ids.detector_id(board_serial, module, channel)``
  with the wiring map's numbers; parameter files may name a detector by id or
  by bolometer name.
- Amps per count (RMS) and bias voltage (RMS) are spt3g's own
  ``counts_to_rms_amps`` and ``bolo_bias_voltage_rms`` of the housekeeping in
  force: they change when an operator changes a gain, a carrier amplitude or
  frequency. The project's gain is a *peak* current per count:
  ``|gain_a_per_count| = sqrt(2) * amps_rms_per_count``.
"""

from __future__ import annotations

import bisect
import logging
from dataclasses import dataclass, field

import numpy as np

from mntes_stream.core.ids import detector_id
from mntes_stream.core.timing import G3_TICK_NS
from mntes_stream.errors import ConfigError, SchemaError
from mntes_stream.g3.settings import G3InputConfig

__all__ = ["COUNTS_24BIT", "Wiring", "HkSnapshot", "HkHistory", "BathHistory", "hk_snapshot",
           "hk_settings", "bath_reading", "g3_time_ns", "invalid_counts", "params_for_wiring", "SQRT2"]

log = logging.getLogger("mntes_stream.g3")

SQRT2 = float(np.sqrt(2.0))
# FLAC packs counts in 24 bits and wraps beyond +-2**23 silently: a value at or beyond it is not a reading.
COUNTS_24BIT = 2**23


def g3_time_ns(t) -> int:
    """ns since the Unix epoch of a G3Time (ticks of 10 ns)."""
    return int(t.time) * G3_TICK_NS


def invalid_counts(x: np.ndarray) -> np.ndarray:
    """True where a counts value is not a reading: NaN, or at/beyond the 24-bit range FLAC keeps."""
    with np.errstate(invalid="ignore"):
        return ~(np.abs(x) < COUNTS_24BIT)


@dataclass(frozen=True, eq=False)
class Wiring:
    """A DfMux wiring map, both ways.

    Attributes
    ----------
    names : tuple of str, length n_bolo
        Bolometer names, sorted by (board, module, channel).
    board, module, channel : ndarray of int64, shape (n_bolo,)
        Board serial, 0-indexed module on the board, 0-indexed channel.
    detector_ids : tuple of str, length n_bolo
    system, transfer_function : str
        spt3g's ReadoutSystem and transfer-function name.
    wiring_map : spt3g.dfmux.DfMuxWiringMap
    """

    names: tuple
    board: np.ndarray
    module: np.ndarray
    channel: np.ndarray
    detector_ids: tuple
    system: str
    transfer_function: str
    wiring_map: object = field(repr=False)
    _by_name: dict = field(default_factory=dict, repr=False)
    _by_id: dict = field(default_factory=dict, repr=False)

    @classmethod
    def from_frame(cls, frame, config: G3InputConfig | None = None, boards=()) -> Wiring:
        """From a Wiring frame (``WiringMap``, ``ReadoutSystem``, ``DfMuxTransferFunction``); only the
        bolometers on ``boards`` (board serials) when given."""
        config = config or G3InputConfig()
        if "WiringMap" not in frame:
            raise SchemaError("G3 Wiring frame without a WiringMap")
        system = str(frame["ReadoutSystem"]) if "ReadoutSystem" in frame else config.readout_system
        tf = str(frame["DfMuxTransferFunction"]) if "DfMuxTransferFunction" in frame else config.transfer_function
        return cls.from_map(frame["WiringMap"], system, tf, boards)

    @classmethod
    def from_map(cls, wm, system: str, transfer_function: str, boards=()) -> Wiring:
        """From a ``DfMuxWiringMap`` (a Wiring frame's, or one spt3g's ``WiringFromJSON`` built from the
        boards' housekeeping); only the bolometers on ``boards`` when given."""
        rows = sorted((int(m.board_serial), int(m.module), int(m.channel), str(name)) for name, m in wm.items())
        if boards:
            rows = [r for r in rows if r[0] in set(boards)]
        if not rows:
            raise SchemaError("G3 wiring map is empty" + (f" on boards {sorted(boards)}" if boards else ""))
        b, m, c, names = (list(x) for x in zip(*rows))
        ids = tuple(detector_id(*t) for t in zip(b, m, c))
        if len(set(ids)) != len(ids):
            raise SchemaError("G3 wiring map maps two bolometers to one readout channel")
        return cls(tuple(names), np.array(b), np.array(m), np.array(c), ids, system, transfer_function, wm,
                   {n: k for k, n in enumerate(names)}, {d: k for k, d in enumerate(ids)})

    def __len__(self) -> int:
        return len(self.names)

    def id_of(self, name: str) -> str:
        """Detector id of a bolometer name (KeyError if not wired)."""
        return self.detector_ids[self._by_name[name]]

    def name_of(self, det_id: str) -> str:
        """Bolometer name of a detector id (KeyError if not wired)."""
        return self.names[self._by_id[det_id]]

    def index_of_names(self, names) -> np.ndarray:
        """Row of each name, shape (n,), -1 for names not wired."""
        return np.array([self._by_name.get(str(n), -1) for n in names], dtype=np.int64)

    def modules(self) -> dict:
        """``(board, module) -> rows`` (int64 indices into :attr:`names`, by channel)."""
        out: dict = {}
        for k, key in enumerate(zip(self.board.tolist(), self.module.tolist())):
            out.setdefault(key, []).append(k)
        return {key: np.array(v, dtype=np.int64) for key, v in out.items()}


@dataclass(frozen=True)
class HkSnapshot:
    """Per-bolometer readout calibration from one DfMux housekeeping frame.

    Attributes
    ----------
    t_ns : int
        Board timestamp of the housekeeping (the first board's, as spt3g uses).
    amps_rms_per_count : ndarray, shape (n_bolo,)
        spt3g ``counts_to_rms_amps``; NaN where the housekeeping lacks the channel.
    v_bias_rms_v : ndarray, shape (n_bolo,)
        spt3g ``bolo_bias_voltage_rms``; NaN likewise.
    settings : ndarray, shape (n_bolo, 8), optional
        The housekeeping values those two depend on (:func:`hk_settings`).
    """

    t_ns: int
    amps_rms_per_count: np.ndarray
    v_bias_rms_v: np.ndarray
    settings: np.ndarray | None = None


_SETTINGS_MOD = ("nuller_gain", "carrier_gain", "demod_gain", "squid_transimpedance")
_SETTINGS_CHAN = ("carrier_amplitude", "carrier_frequency", "demod_frequency", "dan_streaming_enable")


def hk_settings(hkmap, wiring: Wiring) -> np.ndarray:
    """What spt3g's ``counts_to_rms_amps`` and ``bolo_bias_voltage_rms`` read, per wired bolometer.

    Module gains and SQUID transimpedance, channel carrier amplitude and
    frequencies and DAN streaming; shape (n_bolo, 8), NaN where the
    housekeeping lacks the channel. The tree is walked as spt3g's
    ``HousekeepingForBolo`` does (1-indexed mezzanine, module, channel), one
    module object per module instead of one lookup chain per bolometer.
    """
    out = np.full((len(wiring), len(_SETTINGS_MOD) + len(_SETTINGS_CHAN)), np.nan)
    modules: dict = {}
    for k, (b, m, c) in enumerate(zip(wiring.board.tolist(), wiring.module.tolist(), wiring.channel.tolist())):
        try:
            if (b, m) not in modules:
                board = hkmap[b]
                mezz = board.mezz[m // len(board.mezz[1].modules) + 1]
                mod = mezz.modules[m % len(mezz.modules) + 1]
                modules[(b, m)] = (mod, [float(getattr(mod, a)) for a in _SETTINGS_MOD])
            mod, mod_values = modules[(b, m)]
            chan = mod.channels[c + 1]
        except (KeyError, IndexError):
            continue
        out[k] = mod_values + [float(getattr(chan, a)) for a in _SETTINGS_CHAN]
    return out


def hk_snapshot(hkmap, wiring: Wiring, t_fallback_ns: int = 0, previous: HkSnapshot | None = None) -> HkSnapshot:
    """Amps per count and bias of every wired bolometer, from spt3g's own conversion functions.

    When ``previous`` was computed from the same settings (periodic housekeeping
    mostly repeats itself), its values are reused: spt3g's functions cost
    about 0.3 ms per bolometer.
    """
    from mntes_stream.g3.runtime import spt3g

    core, dfmux = spt3g()
    from spt3g.dfmux.unittransforms import bolo_bias_voltage_rms, counts_to_rms_amps

    boards = list(hkmap.values())
    t_ns = g3_time_ns(boards[0].timestamp) if boards else 0
    if t_ns <= 0:
        t_ns = int(t_fallback_ns)
    settings = hk_settings(hkmap, wiring)
    if previous is not None and previous.settings is not None and \
            np.array_equal(previous.settings, settings, equal_nan=True):
        return HkSnapshot(t_ns, previous.amps_rms_per_count, previous.v_bias_rms_v, settings)
    n = len(wiring)
    amps, volts = np.full(n, np.nan), np.full(n, np.nan)
    tf = wiring.transfer_function
    for k, name in enumerate(wiring.names):
        try:
            amps[k] = counts_to_rms_amps(wiring.wiring_map, hkmap, name, wiring.system, tf) / core.G3Units.amp
            volts[k] = bolo_bias_voltage_rms(wiring.wiring_map, hkmap, name, wiring.system, tf) / core.G3Units.V
        except (KeyError, IndexError, ValueError):  # board/module/channel absent from this housekeeping
            continue
    return HkSnapshot(t_ns, amps, volts, settings)


def _same(a: HkSnapshot, b: HkSnapshot) -> bool:
    return (np.array_equal(a.amps_rms_per_count, b.amps_rms_per_count, equal_nan=True)
            and np.array_equal(a.v_bias_rms_v, b.v_bias_rms_v, equal_nan=True))


class HkHistory:
    """Housekeeping snapshots by time; the one in force at a sample is the last at or before it.

    Housekeeping frames are not in time order with the data (the DAQ inserts
    them when it can), so snapshots are kept sorted and looked up by sample
    time. A sample before the first snapshot uses the first (as spt3g's
    ``ConvertTimestreamUnits`` does with the first housekeeping it sees).
    """

    def __init__(self, retention_ns: int = 600 * 10**9):
        self._t: list[int] = []
        self._snaps: list[HkSnapshot] = []
        self.retention_ns = int(retention_ns)

    def prune(self, now_ns: int) -> None:
        """Drop snapshots older than ``retention_ns`` before ``now_ns`` but the one in force then."""
        k = bisect.bisect_right(self._t, int(now_ns) - self.retention_ns) - 1
        if k > 0:
            del self._t[:k], self._snaps[:k]

    def __len__(self) -> int:
        return len(self._t)

    def add(self, snap: HkSnapshot) -> tuple[bool, bool]:
        """Insert (same time: replaced); whether amps per count, and bias, differ from the snapshot before it."""
        k = bisect.bisect_left(self._t, snap.t_ns)
        if k < len(self._t) and self._t[k] == snap.t_ns:
            if _same(self._snaps[k], snap):  # read again (a file read ahead, then streamed)
                return False, False
            self._snaps[k] = snap
        else:
            self._t.insert(k, snap.t_ns)
            self._snaps.insert(k, snap)
        if k == 0:
            return False, False
        prev = self._snaps[k - 1]
        return (not np.array_equal(prev.amps_rms_per_count, snap.amps_rms_per_count, equal_nan=True),
                not np.array_equal(prev.v_bias_rms_v, snap.v_bias_rms_v, equal_nan=True))

    def before(self, t_ns: int) -> HkSnapshot | None:
        """The snapshot in force just before ``t_ns`` (None if none)."""
        k = bisect.bisect_left(self._t, t_ns)
        return self._snaps[k - 1] if k > 0 else None

    def latest(self) -> HkSnapshot | None:
        """The last snapshot by time (None if none)."""
        return self._snaps[-1] if self._snaps else None

    def first(self) -> HkSnapshot:
        if not self._snaps:
            raise ConfigError("no DfMux housekeeping (Housekeeping frame with DfMuxHousekeeping) before the data")
        return self._snaps[0]

    def at(self, t_ns: np.ndarray, rows: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Amps per count and bias (RMS) in force at each sample.

        Parameters
        ----------
        t_ns : ndarray of int64, shape (n_samp,)
        rows : ndarray of int64, shape (n_det,), optional
            Wiring rows (default: all).

        Returns
        -------
        amps_rms_per_count, v_bias_rms_v : ndarray, shape (n_det, n_samp)
        """
        self.first()
        idx = np.clip(np.searchsorted(np.asarray(self._t, dtype=np.int64), t_ns, side="right") - 1, 0, None)
        sel = slice(None) if rows is None else rows
        amps = np.stack([s.amps_rms_per_count[sel] for s in self._snaps])  # (n_snap, n_det)
        volts = np.stack([s.v_bias_rms_v[sel] for s in self._snaps])
        return amps[idx].T, volts[idx].T


def bath_reading(frame, config: G3InputConfig, t_fallback_ns: int) -> tuple[int, float] | None:
    """``(t_ns, K)`` of the bath thermometer in a GcpSlow frame, or None if it has none."""
    from mntes_stream.g3.runtime import spt3g

    core, _ = spt3g()
    head, _, entry = config.t_bath_key.partition(".")
    if head not in frame:
        return None
    value = frame[head]
    try:
        value = value[entry] if entry else value
        value = float(value.value if hasattr(value, "value") else value)
    except (KeyError, TypeError, ValueError):
        return None
    scale = {"G3Units": 1.0 / core.G3Units.K, "K": 1.0, "mK": 1e-3}[config.t_bath_unit]
    t_ns = g3_time_ns(frame[config.t_bath_time_key]) if config.t_bath_time_key in frame else int(t_fallback_ns)
    return t_ns, value * scale


class BathHistory:
    """Bath-temperature readings (linear between readings, held beyond the ends) or a configured default.

    Readings older than ``config.hk_retention_s`` behind the newest are dropped (the one before them kept).
    """

    def __init__(self, config: G3InputConfig):
        self.config = config
        self._t: list[int] = []
        self._v: list[float] = []
        self._retention_ns = int(config.hk_retention_s * 1e9)

    def __len__(self) -> int:
        return len(self._t)

    def add(self, t_ns: int, t_bath_k: float) -> None:
        k = bisect.bisect_left(self._t, t_ns)
        if k < len(self._t) and self._t[k] == t_ns:
            self._v[k] = t_bath_k
        else:
            self._t.insert(k, t_ns)
            self._v.insert(k, t_bath_k)
        # Bounded: readings older than the retention behind the newest go, but the one before them (interpolation).
        cut = bisect.bisect_right(self._t, self._t[-1] - self._retention_ns) - 1
        if cut > 0:
            del self._t[:cut], self._v[:cut]

    @property
    def available(self) -> bool:
        """A reading or a default exists."""
        return bool(self._t) or self.config.t_bath_default_k is not None

    def require(self) -> None:
        """ConfigError unless a reading or a default exists."""
        if not self._t and self.config.t_bath_default_k is None:
            raise ConfigError(
                f"no bath temperature: no GcpSlow frame carries {self.config.t_bath_key!r}; name the thermometer "
                "(t_bath_key, e.g. --t-bath-key CryoStatus.UC_Head) or configure a default (t_bath_default_k)")

    def at(self, t_ns: np.ndarray) -> np.ndarray:
        """Bath temperature (K) at each sample time, shape (n_samp,)."""
        self.require()
        if not self._t:
            return np.full(np.shape(t_ns), float(self.config.t_bath_default_k))
        t0 = self._t[0]
        return np.interp(np.asarray(t_ns, dtype=np.int64) - t0, np.asarray(self._t, dtype=np.int64) - t0, self._v)


def params_for_wiring(params: dict, wiring: Wiring, snap: HkSnapshot, gain_from_hk: bool = True) -> tuple[dict, list[str]]:
    """Detector parameters by detector id, with the readout gain from the housekeeping.

    Parameters
    ----------
    params : dict
        ``DetectorParams`` keyed by detector id or by bolometer name.
    wiring : Wiring
    snap : HkSnapshot
        Housekeeping whose amps per count set ``|gain_a_per_count|`` (the
        phase, i.e. the demodulation phase, stays the file's).
    gain_from_hk : bool
        False: keep the file's gain (a caller scaling the counts per sample
        instead); the housekeeping must still know the channel.

    Returns
    -------
    (dict detector id -> DetectorParams, list of bolometer names without usable parameters)
    """
    out, missing = {}, []
    for k, (name, det_id) in enumerate(zip(wiring.names, wiring.detector_ids)):
        p = params.get(name, params.get(det_id))
        a = snap.amps_rms_per_count[k]
        if p is None or not (np.isfinite(a) and a > 0):
            missing.append(name)
            continue
        gain = p.gain_a_per_count
        if gain_from_hk:
            gain = complex(SQRT2 * a * gain / abs(gain))
        out[det_id] = p.replace(detector_id=det_id, gain_a_per_count=gain)
    return out, missing

"""Live HWP 2f -> 4f leakage of the linear conversion against MNTES, per detector (pure, no I/O).

The monitor keeps, for a bounded set of detectors (``leakage_detectors``,
the first ones in transition in layout order, so they span as few modules
as possible), the last ``leakage_window_s`` of two power series at full rate
in float64: MNTES (the converter's power, as received) and the linear
baseline of the same counts (the monitor's *linear shadow*,
``monitor/shadow.py``). Every ``leakage_every_s`` it measures each
detector with :func:`mntes_stream.core.leakage.leakage_between` ``(t,
linear, mntes)`` over the samples the two share: the effective nonlinearity
the linear conversion would have left, which MNTES removed. Readout noise
and any 4f line of the sky are in both series and cancel.

What is never shown as a number: a detector without a 2f line
(``no_2f_line``), too short a window (``too_few_samples``), a detector the
linear baseline cannot take (``no_linear_baseline``: latched or normal at
its nominal operating point), one whose linear shadow has no samples yet
(``no_linear_shadow``); a value within 3 sigma of zero is given as its
3-sigma upper limit. MNTES's own residual needs the true optical power, which
a live stream does not carry: ``mntes-stream leakage REC --truth NPZ`` measures
it on a simulator's recording.
"""

from __future__ import annotations

import math

import numpy as np

from mntes_stream.core.ids import parse_detector_id
from mntes_stream.core.leakage import REQUIREMENT_PER_PW, STATUS_NO_2F, leakage_between, median_nl, refine_f_hwp
from mntes_stream.errors import ConfigError
from mntes_stream.monitor.analysis import estimate_f_hwp, welch_psd
from mntes_stream.monitor.history import Ring

__all__ = ["STATUS_NO_SHADOW", "STATUS_NO_BASELINE", "MNTES_LIVE", "LiveLeakage"]

STATUS_NO_SHADOW = "no_linear_shadow"      # no linear power of this detector yet (no parameters or counts)
STATUS_NO_BASELINE = "no_linear_baseline"  # latched or normal at its nominal point: no linearisation
MNTES_LIVE = ("not measurable live: MNTES's own residual needs the true optical power "
              "(mntes-stream leakage REC --truth NPZ on a simulator's recording)")
_F_ROWS = 8  # detectors whose MNTES power locates f_HWP
_REFINE_EVERY = 6  # measurements between two refinements of f_HWP (cheap now, but the HWP is steady)


def _num(x, digits: int = 4):
    return None if x is None or not math.isfinite(x) else float(f"{x:.{digits}g}")


class LiveLeakage:
    """The measured detectors' two power series and the last measurement.

    Parameters
    ----------
    max_detectors : int
        Detectors measured (0: none).
    window_s : float
        Power kept and fitted per detector.
    every_s : float
        Measurement period (data clock of the tick's caller).
    max_rate_hz : float
        Caps the rings (window x this), as every monitor ring.
    """

    def __init__(self, max_detectors: int, window_s: float, every_s: float, max_rate_hz: float):
        self.max_detectors = int(max_detectors)
        self.window_s = float(window_s)
        self.every_s = float(every_s)
        self._capacity = int(math.ceil(window_s * max_rate_hz))
        self.chosen: list[str] = []
        self.module_keys: frozenset[tuple[int, int]] = frozenset()  # (board, module) of the chosen
        self.no_baseline: set[str] = set()
        self._mntes: dict[str, Ring] = {}
        self._linear: dict[str, Ring] = {}
        self._next_ns: int | None = None
        self.evaluations = 0
        self._refined: tuple[float | None, float] | None = None  # (guess, refined f_HWP)
        self.shadow_state = ""  # what the linear shadow is doing (monitor/shadow.py), shown with the result
        self.last: dict = self._empty("waiting for power")

    # ------------------------------------------------------------------ what is measured

    def choose(self, candidates: list[str]) -> bool:
        """Fix the measured detectors once (the first ``max_detectors`` of ``candidates``); True if they changed."""
        if self.chosen or not candidates or self.max_detectors <= 0:
            return False
        self.chosen = list(candidates[: self.max_detectors])
        self.module_keys = frozenset(parse_detector_id(d)[:2] for d in self.chosen)
        for d in self.chosen:
            self._mntes[d] = Ring(1, self._capacity, np.float64)
            self._linear[d] = Ring(1, self._capacity, np.float64)
        return True

    def modules(self) -> list[tuple[int, int]]:
        """``(board, module)`` of the measured detectors: whose counts the linear shadow needs."""
        return sorted(self.module_keys)

    def add(self, which: str, det_ids, t_ns: np.ndarray, p_w: np.ndarray) -> None:
        """Power of a chunk: ``which`` "mntes" or "linear", ids (n_ch,), times (n,), power (n_ch, n)."""
        rings = self._mntes if which == "mntes" else self._linear
        if not rings or t_ns.size == 0:
            return
        for i, d in enumerate(det_ids):
            ring = rings.get(d)
            if ring is None:
                continue
            newest = ring.newest_t_ns
            if newest is not None and int(t_ns[0]) <= newest:
                if int(t_ns[-1]) < newest - int(self.window_s * 1e9):
                    ring.clear()  # a replay started over
                else:
                    continue  # late or repeated: the rings stay time-ordered
            ring.append(t_ns, np.asarray(p_w[i:i + 1], dtype=np.float64))

    # ------------------------------------------------------------------ measuring

    def due(self, now_ns: int) -> bool:
        return bool(self.chosen) and (self._next_ns is None or int(now_ns) >= self._next_ns)

    def evaluate(self, now_ns: int, f_hwp_hz: float | None) -> dict:
        """:meth:`snapshot` then :meth:`measure`, kept as :attr:`last`."""
        self.last = self.measure(self.snapshot(now_ns), now_ns, f_hwp_hz)
        return self.last

    def snapshot(self, now_ns: int) -> dict:
        """Copies of each chosen detector's series on the samples both share, last ``window_s``:
        ``{id: (t_ns (m,), linear (m,), mntes (m,))}``. Cheap: the caller holds its lock for this only."""
        self._next_ns = int(now_ns) + int(self.every_s * 1e9)
        pairs = {}
        for d in self.chosen:
            t_m, p_m = self._mntes[d].read()
            t_l, p_l = self._linear[d].read()
            common, im, il = np.intersect1d(t_m, t_l, assume_unique=True, return_indices=True)
            if common.size:
                keep = common >= common[-1] - int(self.window_s * 1e9)
                pairs[d] = (common[keep], p_l[0, il[keep]], p_m[0, im[keep]])
        return pairs

    def measure(self, pairs: dict, now_ns: int, f_hwp_hz: float | None) -> dict:
        """The measurement of a :meth:`snapshot` (JSON-ready; the fits take ~10-50 ms per detector, so
        the monitor runs this outside its lock).

        Parameters
        ----------
        pairs : dict
            From :meth:`snapshot`.
        now_ns : int
        f_hwp_hz : float or None
            Configured HWP frequency (refined on the 2f line), or None: estimated from the MNTES spectra.
        """
        self.evaluations += 1
        t_ref = min((p[0][0] for p in pairs.values() if p[0].size), default=None)
        f_hz, source = self._f_hwp(pairs, t_ref, f_hwp_hz)
        rows, results = [], []
        for d in self.chosen:
            row = {"id": d}
            if d in self.no_baseline:
                row["status"] = STATUS_NO_BASELINE
            elif d not in pairs or pairs[d][0].size == 0:
                row["status"] = STATUS_NO_SHADOW
            elif f_hz is None:
                row["status"] = STATUS_NO_2F
            else:
                t_ns, lin, mn = pairs[d]
                r = leakage_between((t_ns - t_ref) * 1e-9, lin, mn, f_hz)
                results.append(r)
                row.update(status=r.status, window_s=_num(r.window_s), samples=r.n_samples,
                           a2_fw=_num(abs(r.line_2f.amplitude_w) * 1e15) if r.line_2f is not None else None)
                if r.nl_per_w is not None:
                    row.update(nl_per_pw=_num(r.nl_per_pw), sigma_per_pw=_num(r.sigma_nl_per_pw, 2),
                               resolved=bool(r.resolved),
                               bound_per_pw=None if r.resolved else _num(abs(r.nl_per_pw) + 3 * r.sigma_nl_per_pw, 2))
            rows.append(row)
        med = median_nl(results)
        return {
            "enabled": True, "t_ns": int(now_ns), "f_hwp_hz": _num(f_hz, 7), "f_hwp_source": source,
            "window_s": self.window_s, "every_s": self.every_s, "requirement_per_pw": REQUIREMENT_PER_PW,
            "detectors": rows,
            "median": {"value_per_pw": _num(med.value_per_pw), "sigma_per_pw": _num(med.sigma_per_pw, 2),
                       "bound_per_pw": None if med.resolved else _num(med.bound_per_pw, 2),
                       "n_measured": med.n_detectors, "n_resolved": med.n_resolved},
            "mntes": MNTES_LIVE, "shadow": self.shadow_state,
        }

    def _f_hwp(self, pairs: dict, t_ref, f_hwp_hz: float | None) -> tuple[float | None, str]:
        """The configured or spectrally estimated f_HWP, refined on the MNTES 2f line (as ``leakage`` does)."""
        if not pairs or t_ref is None:
            return None, "no samples"
        longest = max(pairs.values(), key=lambda p: p[0].size)[0]
        rows = [np.interp(longest, p[0], p[2], left=np.nan, right=np.nan) for p in pairs.values()][:_F_ROWS]
        rows = np.array(rows)
        t_s = (longest - t_ref) * 1e-9
        if longest.size < 64:
            return None, "too few samples"
        guess, source = f_hwp_hz, "configured"
        if guess is None:
            fs_hz = 1.0 / float(np.median(np.diff(t_s)))
            good = rows[np.mean(np.isfinite(rows), axis=1) > 0.9]
            guess = estimate_f_hwp(*welch_psd(good, fs_hz, segments=1)) if good.size else None
            if guess is None:
                return None, "no HWP comb in the power spectrum"
            source = "estimated"
        # The HWP turns at a steady rate: refined again only when the guess moves or
        # every _REFINE_EVERY measurements; in between the last refined value stands.
        cached = self._refined
        if cached is not None and cached[0] == guess and self.evaluations % _REFINE_EVERY != 1:
            return cached[1], source + ", refined on the 2f line"
        try:
            f = refine_f_hwp(t_s, rows, guess)
        except ConfigError:
            return guess, source
        self._refined = (guess, f)
        return f, source + ", refined on the 2f line"

    def focal(self) -> dict[str, float]:
        """``{detector id: |nl| pW^-1}`` of the last measurement, where resolved (else its 3-sigma bound)."""
        out = {}
        for r in self.last.get("detectors", []):
            v = abs(r["nl_per_pw"]) if r.get("resolved") else r.get("bound_per_pw")
            if v is not None:
                out[r["id"]] = v
        return out

    def _empty(self, why: str) -> dict:
        return {"enabled": self.max_detectors > 0, "t_ns": None, "why": why if self.max_detectors > 0 else
                "off (leakage_detectors = 0)", "window_s": self.window_s, "every_s": self.every_s,
                "requirement_per_pw": REQUIREMENT_PER_PW, "detectors": [], "mntes": MNTES_LIVE,
                "shadow": self.shadow_state}

    def waiting(self, why: str) -> None:
        """Say why there is no measurement yet (until the first one)."""
        if self.last.get("t_ns") is None:
            self.last = self._empty(why)

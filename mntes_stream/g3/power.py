"""``OpticalPower``: a spt3g pipeline module that appends MNTES optical power to Scan frames.

Use it after the collator in any ``core.G3Pipeline``::

    pipe.Add(core.G3Reader, filename="run.g3")
    pipe.Add(dfmux.DfMuxCollator)            # if the file holds raw Timepoints
    pipe.Add(mntes_stream.g3.OpticalPower, params="params.toml")
    pipe.Add(core.G3Writer, filename="out.g3")

Each Scan frame with ``RawTimestreams_I``/``_Q`` gains ``MntesOpticalPower``
(G3TimestreamMap, units Power, float64 W, keys = bolometer names) and
``MntesFlags`` (G3TimestreamMap of int32, the ``core.flags`` bits); every
frame passes on. The readout gain and bias of each sample are the DfMux
housekeeping in force at that sample (spt3g's own conversion functions), so
a gain change mid-run applies from the sample at or after its timestamp.

With detector parameters the module is the live converter's pipeline
(``pipeline.ConverterPipeline``, its converter from ``pipeline.build``: the
table cache too) behind the G3 translator the bridge
uses (``g3.translate.FrameTranslator``): each Scan frame becomes one counts
chunk per module, housekeeping (DfMux bias, the bath thermometer of GcpSlow
frames) becomes the same housekeeping messages, and the power comes out of
the same stages with the same flags (HK_STALE, HK_MISSING, ...) and bounded
histories as ``convert RUN.g3 OUT.mcap``. A Scan frame waits in the module
until its power is out (the pipeline waits for the housekeeping that
brackets a chunk); frames leave in their order. A gain change in the DfMux
housekeeping rescales the counts to the parameters' gain from its sample on.

Kind ``electrical`` without parameters is ``P = -I * a(t) * V(t)``: minus
spt3g's ``ConvertTimestreamUnits(..., Power)`` (optical power = constant -
electrical power; the constant is unknown without parameters and taken as 0).
"""

from __future__ import annotations

import logging
from collections import deque
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from mntes_stream.core import flags as fl
from mntes_stream.core.convert import CONVERTER_KINDS
from mntes_stream.errors import ConfigError
from mntes_stream.g3.counts import scan_block
from mntes_stream.g3.mapping import (
    BathHistory,
    HkHistory,
    Wiring,
    bath_reading,
    hk_snapshot,
    invalid_counts,
    params_for_wiring,
)
from mntes_stream.g3.runtime import spt3g
from mntes_stream.g3.settings import G3InputConfig
from mntes_stream.g3.translate import FrameTranslator
from mntes_stream.io import keys
from mntes_stream.pipeline.build import ConverterSpec, build_converter, default_table_cache
from mntes_stream.pipeline.config import PipelineConfig
from mntes_stream.pipeline.pipeline import ConverterPipeline
from mntes_stream.pipeline.runner import Runner

__all__ = ["OpticalPower", "POWER_KEY", "FLAGS_KEY", "load_g3_params"]

log = logging.getLogger("mntes_stream.g3")

POWER_KEY = "MntesOpticalPower"
FLAGS_KEY = "MntesFlags"


def load_g3_params(params) -> dict | None:
    """Parameters as a dict (keyed by detector id or bolometer name) from a path, a dict, or None."""
    if params is None:
        return None
    if isinstance(params, (str, Path)):
        from mntes_stream.io.paramfile import load_params

        return load_params(params)
    if isinstance(params, Mapping):
        return dict(params)
    raise ConfigError(f"params must be a parameter file or a mapping, got {type(params).__name__}")


class OpticalPower:
    """Append ``MntesOpticalPower`` and ``MntesFlags`` to each Scan frame.

    Parameters
    ----------
    params : path, mapping or None
        Detector parameters keyed by detector id or bolometer name. None is
        allowed for ``kind="electrical"`` only.
    kind : str
        A converter kind (``core.convert.CONVERTER_KINDS``); default ``table``.
    config : G3InputConfig, optional
        Bath-temperature source, field, transfer-function defaults.
    preload : iterable of frames, optional
        Wiring, Housekeeping and GcpSlow frames of the whole run, read ahead
        (housekeeping is not in time order with the scans: a reading taken
        during a scan may be written after it). With parameters only its
        bath readings are used: whether the run has a thermometer.
    pipeline_config : PipelineConfig, optional
        The converter pipeline's settings (housekeeping staleness, ...); default
        as ``convert`` uses them.
    table_cache : path, optional
        Where table banks built from parameters are kept, as the converter
        service keeps them (``...``: its default; None: always build). Build
        options among ``converter_options`` build the bank anew.
    """

    def __init__(self, params=None, kind: str = "table", config: G3InputConfig | None = None, preload=(),
                 input_i: str = "RawTimestreams_I", input_q: str = "RawTimestreams_Q", output: str = POWER_KEY,
                 flags_output: str = FLAGS_KEY, pipeline_config: PipelineConfig | None = None,
                 table_cache=..., **converter_options):
        if kind not in CONVERTER_KINDS:
            raise ConfigError(f"unknown kind {kind!r} (known: {', '.join(CONVERTER_KINDS)})")
        self.params = load_g3_params(params)
        if self.params is None and kind != "electrical":
            raise ConfigError(f"kind {kind!r} needs detector parameters (only 'electrical' works without)")
        self.kind = kind
        self.config = config or G3InputConfig()
        self.input_i, self.input_q, self.output, self.flags_output = input_i, input_q, output, flags_output
        self.converter_options = converter_options
        self.table_cache = default_table_cache() if table_cache is ... else str(table_cache or "")
        self.wiring: Wiring | None = None
        self.hk = HkHistory(int(self.config.hk_retention_s * 1e9))
        self.bath = BathHistory(self.config)
        self._pending_hk: list = []
        self._converter = None
        self._t_last_ns = 0
        self.skipped: tuple = ()
        self.scans = 0
        self.samples = 0
        self.gain_changes = 0
        self.rejected: dict[str, int] = {}  # frames it could not use, by reason (dropped from the output)
        self._pipe: ConverterPipeline | None = None
        self._runner: Runner | None = None
        self._tr: FrameTranslator | None = None
        if self.params is not None:
            self.pipeline_config = pipeline_config or PipelineConfig()
            # Typed: counts chunks and power chunks pass as objects, never as bytes (ConverterPipeline(typed=True)).
            self._tr = FrameTranslator(self.pipeline_config.setup, self.config, typed=True)
            self._early: deque = deque(maxlen=10_000)  # housekeeping before the first scan (the pipeline's input)
            self._held: deque[list] = deque()  # [frame, wanted (board, module, seq), power chunks got]
            self._wanted: dict[tuple, list] = {}
            self._names: dict[str, str] = {}
            self._keep: frozenset = frozenset()
        for frame in preload:
            if self._tr is None or frame.type == spt3g()[0].G3FrameType.GcpSlow:
                self._guarded(self._metadata, frame)

    def _guarded(self, method, frame) -> bool:
        """``method(frame)``; a frame it cannot use (wrong class, empty map, undecodable) counted, False."""
        from mntes_stream.g3.translate import check_frame
        from mntes_stream.g3.wire import BadFrame

        try:
            check_frame(frame)
            method(frame)
            return True
        except BadFrame as exc:
            reason, text = exc.reason, str(exc)
        except (RuntimeError, MemoryError) as exc:
            reason, text = "undecodable", str(exc).split(" (in ", 1)[0]
        except (TypeError, ValueError, KeyError, AttributeError, IndexError) as exc:
            if isinstance(exc, ConfigError):
                raise  # ours: no parameters, no bath temperature ... is the run's problem, not a frame's
            reason, text = "bad_content", f"{type(exc).__name__}: {exc}"
        self.rejected[reason] = self.rejected.get(reason, 0) + 1
        log.warning("G3 %s frame dropped (%s): %s", frame.type, reason, text)
        return False

    # -- frames -------------------------------------------------------------------------------
    def _metadata(self, frame) -> bool:
        core, _ = spt3g()
        ft = frame.type
        if ft == core.G3FrameType.Wiring:
            wiring = Wiring.from_frame(frame, self.config)
            if self.wiring is None or wiring.names != self.wiring.names or \
                    not np.array_equal(wiring.detector_ids, self.wiring.detector_ids):
                self.wiring = wiring
                self.hk = HkHistory(int(self.config.hk_retention_s * 1e9))
                for hkmap, t in self._pending_hk:
                    self._add_hk(hkmap, t)
                self._pending_hk = []
            return True
        if ft == core.G3FrameType.Housekeeping and "DfMuxHousekeeping" in frame:
            if self.wiring is None:  # the wiring may follow: keep it until then
                self._pending_hk.append((frame["DfMuxHousekeeping"], self._t_last_ns))
            else:
                self._add_hk(frame["DfMuxHousekeeping"], self._t_last_ns)
            return True
        if ft == core.G3FrameType.GcpSlow:
            r = bath_reading(frame, self.config, self._t_last_ns)
            if r is not None:
                self.bath.add(*r)
            return True
        return False

    def _add_hk(self, hkmap, t_fallback_ns: int) -> None:
        if any(self.hk.add(hk_snapshot(hkmap, self.wiring, t_fallback_ns, self.hk.latest()))):
            self.gain_changes += 1

    def __call__(self, frame):
        """Append the power to a Scan frame; a frame it cannot use is dropped and counted (``rejected``)."""
        if self._tr is not None:
            return self._through_pipeline(frame)
        if not self._guarded(self._process, frame):
            return []
        return None

    # -- with parameters: the converter pipeline --------------------------------------------------
    def _through_pipeline(self, frame):
        core, _ = spt3g()
        ft, tr = frame.type, self._tr
        if ft == core.G3FrameType.EndProcessing:
            self._route(self._runner.finish() if self._runner is not None else [])
            return self._release(True) + [frame]
        if ft == core.G3FrameType.Scan and self._pipe is None and self.input_i in frame:
            if tr.wiring is None:
                raise ConfigError("G3 Scan frame before any Wiring frame: cannot tell which bolometer is which")
            self._build()
        before = sum(tr.counters.rejected.values())
        msgs = tr.timed(tr.accept, frame)
        self._count_rejected()
        if sum(tr.counters.rejected.values()) != before:
            return []  # counted by reason; not passed on
        if ft == core.G3FrameType.GcpSlow and msgs:
            self.bath.add(msgs[0][0], 0.0)  # a thermometer: no default readings from here on
        counts = [m for m in msgs if keys.kind_of(m[1]) == "counts"]
        if counts and not len(self.bath) and self.config.t_bath_default_k is not None:
            msgs = tr.timed(tr.default_bath, counts[0][0]) + msgs  # as convert RUN.g3 OUT.mcap does
        if not counts and not self._held:
            self._feed(msgs)
            return None
        entry = [frame, set(), {}]
        for _, _, c in counts:
            want = (c.board, c.module, c.seq)
            entry[1].add(want)
            self._wanted[want] = entry
        self._held.append(entry)
        self._feed(msgs)
        return self._release(False)

    def _build(self) -> None:
        """The converter and its pipeline for the wired bolometers with parameters (at the first scan)."""
        tr = self._tr
        pdict, missing = params_for_wiring(self.params, tr.wiring, tr.hk.first(), gain_from_hk=True)
        if missing:
            log.warning("%d wired bolometer(s) without parameters or housekeeping, skipped: %s%s", len(missing),
                        ", ".join(missing[:8]), " ..." if len(missing) > 8 else "")
        self.skipped = tuple(missing)
        if not pdict:
            raise ConfigError("no wired bolometer has parameters: are they keyed by bolometer name or detector id?")
        # Later gain changes rescale the counts to the parameters' gain (the translator does, as for the bridge).
        tr.set_gain_reference({d: abs(p.gain_a_per_count) for d, p in pdict.items()})
        spec = ConverterSpec(kind=self.kind, params=tuple(pdict.items()), table_cache=self.table_cache,
                             options=tuple(self.converter_options.items()))
        self._converter = build_converter(spec).converter
        self._pipe = ConverterPipeline(self._converter, self.pipeline_config, params=list(pdict.values()), clock=None,
                                       typed=True)
        self._runner = Runner.around(self._pipe)
        self._names = dict(zip(tr.wiring.detector_ids, tr.wiring.names))
        self._keep = frozenset(pdict)
        early, self._early = list(self._early), deque(maxlen=10_000)
        self._feed(early)

    def _feed(self, msgs) -> None:
        """Messages ``(t_ns, key, payload)`` into the pipeline, received at their data time (as offline)."""
        if self._pipe is None:
            self._early.extend(msgs)
            return
        if msgs:
            self._route(self._runner.feed_batch([(k, p, t) for t, k, p in msgs], msgs[-1][0]))

    def _route(self, outs) -> None:
        for key, chunk, _ in outs:
            if keys.kind_of(key) != "power":
                continue
            entry = self._wanted.pop((chunk.board, chunk.module, chunk.seq), None)
            if entry is not None:
                entry[2][(chunk.board, chunk.module)] = chunk

    def _release(self, final: bool) -> list:
        """Held frames whose power is out, in their order (all of them when nothing is held in the pipeline)."""
        idle = final or (self._pipe is not None and self._pipe.pending == 0 and not self._pipe.set_aside)
        out = []
        while self._held and (idle or len(self._held[0][2]) == len(self._held[0][1])):
            frame, wanted, got = self._held.popleft()
            for w in wanted:
                self._wanted.pop(w, None)  # not converted (the pipeline's ledger says why): rows absent
            if wanted:
                self._attach(frame, got)
            out.append(frame)
        self.gain_changes = self._tr.counters.gain_changes + self._tr.counters.bias_changes
        return out

    def _attach(self, frame, got: dict) -> None:
        core, _ = spt3g()
        names, p, f = [], [], []
        for stream in sorted(got):
            chunk = got[stream]
            rows = [r for r, d in enumerate(chunk.detector_ids) if d in self._keep]
            names += [self._names[chunk.detector_ids[r]] for r in rows]
            p.append(chunk.p_opt_w[rows])
            f.append(chunk.flags[rows])
        if not names:
            return
        p, f = np.concatenate(p), np.concatenate(f)
        start, stop = frame[self.input_i].start, frame[self.input_i].stop
        frame[self.output] = core.G3TimestreamMap(names, np.ascontiguousarray(p), start, stop,
                                                  core.G3TimestreamUnits.Power)
        frame[self.flags_output] = core.G3TimestreamMap(names, f.astype(np.int32), start, stop)
        self.scans += 1
        self.samples += p.size

    def _count_rejected(self) -> None:
        self.rejected = dict(self._tr.counters.rejected)

    @property
    def ledger(self):
        """The pipeline's ledger of the counts chunks (None before the first scan)."""
        return self._pipe.ledger_now() if self._pipe is not None else None

    def _process(self, frame) -> None:
        core, _ = spt3g()
        if self._metadata(frame) or frame.type != core.G3FrameType.Scan:
            return
        if self.wiring is None:
            raise ConfigError("G3 Scan frame before any Wiring frame: cannot tell which bolometer is which")
        blk = scan_block(frame, self.wiring, self.input_i, self.input_q)
        if blk is None:
            return
        self._t_last_ns = int(blk.t_ns[-1]) if blk.n_samples else self._t_last_ns
        names, p, f = self.convert_block(blk)
        self.hk.prune(int(blk.t_ns[0]))  # bounded: the snapshot in force now and the retention before it
        start, stop = frame[self.input_i].start, frame[self.input_i].stop  # the input's span, as spt3g keeps it
        frame[self.output] = core.G3TimestreamMap(list(names), p, start, stop, core.G3TimestreamUnits.Power)
        frame[self.flags_output] = core.G3TimestreamMap(list(names), f.astype(np.int32), start, stop)
        self.scans += 1
        self.samples += p.size

    @property
    def needs_bath(self) -> bool:
        """True for the MNTES kinds (the bath temperature enters the power balance)."""
        return self.kind in ("table", "grid", "exact")

    # -- without parameters: kind electrical -----------------------------------------------------
    def convert_block(self, blk):
        """Minus spt3g's electrical power of a :class:`~mntes_stream.g3.counts.ScanBlock` (kind ``electrical``
        without parameters; with parameters the pipeline converts).

        Returns
        -------
        names : list of str, length n_det
        p_opt_w : ndarray of float64, shape (n_det, n_samp)
        flags : ndarray of uint16, shape (n_det, n_samp)
        """
        rows = blk.rows
        ci = blk.counts_i
        bad = invalid_counts(ci) | invalid_counts(blk.counts_q)
        amps, volts = self.hk.at(blk.t_ns, rows)
        names = [self.wiring.names[r] for r in rows]
        with np.errstate(invalid="ignore"):
            p = -(ci * amps * volts)
        f = np.where(bad | ~np.isfinite(p), fl.INVALID_INPUT, 0).astype(np.uint16)
        p[f != 0] = np.nan
        return names, p, f

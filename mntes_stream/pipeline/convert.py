"""The converter's stages from conversion on: conversion, flags, encoding (no I/O).

A released chunk comes as a ``Ready`` (its rows and its housekeeping at every
sample, ``pipeline.stages.Environment``); :class:`Convert` gathers them until the end of
the batch and converts them in as few converter calls as may be;
:class:`Flags` completes the flags and makes flagged power NaN; :class:`Encode`
makes each chunk's power message and books it. See ``pipeline.items`` for
what flows between stages.
"""

from __future__ import annotations

import logging
import threading
import time

import numpy as np

from mntes_stream.core import flags as fl
from mntes_stream.core.convert import EnvironmentBlock
from mntes_stream.core.uncertainty import NoiseWindow, low_responsivity_block, sigma_p_block
from mntes_stream.io import keys
from mntes_stream.io.lean import PowerEncoder
from mntes_stream.pipeline.items import Converted, End, Flagged, Output, Ready, Run
from mntes_stream.pipeline.stages import Books

__all__ = ["Convert", "Encode", "Flags"]

# A run is split across threads only from this many samples (rows x samples): below, a thread hand-over
# (tens of microseconds) costs more than the kernel time it saves.
_SPLIT_SAMPLES = 200_000

log = logging.getLogger("mntes_stream.converter")


def _layout(group: list[Ready]) -> tuple | None:
    """A group's rows, module by module (None when a module appears twice: not merged)."""
    # A chunk's ``ids`` is the one tuple ``Environment`` keeps per module and channel list: the same object is
    # the same rows (every Ready of the batch holds its tuple, so no id is reused within it), and a list
    # cached anew only splits a run in two (the same power, one more call), never merges unlike rows.
    rows = sorted((r.chunk.board, r.chunk.module, id(r.ids), r.v_bias is None) for r in group)
    return tuple(rows) if len({row[:2] for row in rows}) == len(rows) else None


def _runs(groups: list[list[Ready]]) -> list[list[list[Ready]]]:
    """Groups with one row layout, together, in the order each layout first appears.

    A stream's chunks can change order here: a step whose modules were aligned
    on both sides of a new housekeeping reading is two groups, each joining the
    run of its layout, so a stream may be in two runs of one batch. ``Flags``
    puts the converted chunks back in their release order.
    """
    runs: dict[object, list[list[Ready]]] = {}
    for k, group in enumerate(groups):
        layout = _layout(group)
        runs.setdefault(k if layout is None else layout, []).append(group)
    return list(runs.values())


class Convert:
    """Released chunks, gathered until the end of the batch, through the converter in as few calls as may be.

    The modules of one readout step share their sample times, hence their
    aligned bath temperature and field (the same cached arrays): a *group*.
    The groups with the same rows (modules and channel lists) form a *run*
    (:func:`_runs`), converted as one block whose rows are the detectors and whose
    columns are the samples of every step in turn: a backlog of steps costs
    the converter's per-call work once, and each detector's tables are
    looked up once per run rather than once per step (on a 5,000-detector
    focal plane those lookups miss the cache). Rows and samples are
    independent, so the power is the same as chunk by chunk. With ``threads``
    > 1 a large run is split by modules across threads (the kernel releases
    the GIL). A run whose call fails is converted chunk by chunk, which finds
    the chunk that failed: it is flagged INVALID_INPUT and counted.
    """

    name = "convert"
    takes, gives = (Ready,), (Run, Converted)

    def __init__(self, books: Books, converter, threads: int = 1, noise=None, sigma_p: bool = False):
        self.books, self.converter, self._threads, self._noise = books, converter, threads, noise
        self._sigma_p = sigma_p and noise is not None
        self._window = self._index = None
        if noise is not None and noise.settings.readout_noise == "measured":
            # Each channel's white noise from its own counts (core.uncertainty.NoiseWindow); the configured
            # noise until a channel's first window is complete.
            self._window = NoiseWindow(len(converter.detector_ids), noise.settings.noise_window_samples)
            self._index = {d: k for k, d in enumerate(converter.detector_ids)}
            self._configured = noise
        self._executor = None
        self._held: list[Ready] = []
        # CPU seconds inside converter calls (each calling thread's own CPU, summed over threads): what a
        # benchmark subtracts from the converter's CPU to see its per-chunk cost around the kernel.
        self.kernel_cpu_s = 0.0
        # Converter calls and the chunks they converted: chunks per call is how much of a batch one call took
        # (the kernel's cost per chunk falls as it grows: each detector's tables are looked up once per call).
        self.kernel_calls = self.kernel_chunks = 0
        self._ids_cache: dict[tuple, tuple] = {}
        self._kernel_lock = threading.Lock()

    @property
    def noise(self):
        """The noise model in use now (None: no LOW_RESPONSIVITY); with measured noise, renewed as windows complete."""
        return self._noise

    def _measure(self, r: Ready) -> bool:
        """Add a chunk's counts to the live noise window; True when an estimate was renewed."""
        rows = np.fromiter((self._index.get(d, -1) for d in r.ids), dtype=np.int64, count=len(r.ids))
        return self._window.add(rows, r.chunk.counts_i, r.chunk.counts_q).size > 0

    def _renew_noise(self) -> None:
        """The noise model with every measured channel's live white noise (counts rms times |gain|)."""
        base = self._configured
        sig = self._window.sigma_counts
        have = np.isfinite(sig)
        noise_a = np.where(have, np.nan_to_num(sig) * np.abs(base.gain_a_per_count), base.readout_noise_a)
        source = tuple("measured:live" if h else s for h, s in zip(have, base.source))
        self._noise = base.with_noise(noise_a, source, f"live, {self._window.window} second differences per channel")

    def __call__(self, items: list) -> list:
        out = []
        renewed = False
        for item in items:
            if type(item) is Ready:
                item.order = len(self._held)
                self._held.append(item)
                if self._window is not None:
                    renewed |= self._measure(item)
                continue
            if type(item) is End:
                if renewed:
                    self._renew_noise()
                    renewed = False
                self._convert(out)
            out.append(item)
        return out

    def _convert(self, out: list) -> None:
        held, self._held = self._held, []
        groups: dict[tuple, list[Ready]] = {}
        for r in held:
            groups.setdefault((id(r.t_bath), id(r.b_field), r.v_bias is None, r.late), []).append(r)
        for run in _runs(list(groups.values())):
            parts = self._run(run) if len(run) > 1 or len(run[0]) > 1 else None
            if parts is not None:
                out.append(parts)
            else:
                out += [self._one(r) for group in run for r in group]

    def _run(self, run: list[list[Ready]]) -> Run | None:
        """Converter calls for a run of groups (None: convert them one by one)."""
        orders = [sorted(range(len(g)), key=lambda k, g=g: (g[k].chunk.board, g[k].chunk.module)) for g in run]
        n_mod = len(orders[0])
        cols = np.cumsum([0] + [g[0].chunk.counts_i.shape[1] for g in run])
        n_rows = sum(r.chunk.channels.size for r in run[0])
        k = min(self._threads, n_mod) if n_rows * int(cols[-1]) >= _SPLIT_SAMPLES else 1
        bounds = [round(i * n_mod / k) for i in range(k + 1)]
        parts = [(bounds[i], bounds[i + 1]) for i in range(k)]
        try:
            if k == 1:
                done = [self._part(run, orders, 0, n_mod)]
            else:
                futures = [self._pool().submit(self._part, run, orders, m0, m1) for m0, m1 in parts[1:]]
                done = [self._part(run, orders, *parts[0])] + [f.result() for f in futures]
        except Exception:  # noqa: BLE001 - find out which chunk it was: one by one, each failure counted
            return None
        return Run(run, orders, cols, [(m0, m1, *d) for (m0, m1), d in zip(parts, done)])

    def _part(self, run: list[list[Ready]], orders: list[list[int]], m0: int, m1: int) -> tuple:
        """Modules ``m0:m1`` of the run (in stream order) through one converter call.

        Returns p_opt and flags (rows, samples), the environment flags, the rows' chunks of the first
        group and sigma_P (or None). Raises on any failure (the caller then converts chunk by chunk).
        """
        rows = [run[0][k] for k in orders[0][m0:m1]]  # the part's row layout, module by module
        steps = len(run)

        def block(field):  # modules stacked, each module's steps side by side
            if steps == 1:
                return np.concatenate([field(r) for r in rows])
            return np.concatenate([np.concatenate([field(g[o[m]]) for g, o in zip(run, orders)], axis=1)
                                   for m in range(m0, m1)])

        ci = block(lambda r: r.chunk.counts_i)
        cq = block(lambda r: r.chunk.counts_q)
        t_bath = np.concatenate([g[0].t_bath for g in run]) if steps > 1 else run[0][0].t_bath
        b_field = np.concatenate([g[0].b_field for g in run]) if steps > 1 else run[0][0].b_field
        if rows[0].v_bias is None:
            v_bias = None
            env_flags = np.concatenate([g[0].env_flags for g in run]) if steps > 1 else run[0][0].env_flags
        else:
            v_bias = block(lambda r: r.v_bias)
            env_flags = block(lambda r: np.broadcast_to(r.env_flags, r.chunk.counts_i.shape))
        env = EnvironmentBlock(t_bath_k=t_bath, b_field_t=b_field, v_thev_v=v_bias, flags=env_flags)
        ids = self._ids(rows)
        p_opt, flags, sigma = self._converted(ids, ci, cq, env, len(rows) * steps)
        if p_opt.shape != ci.shape or flags.shape != ci.shape:
            raise ValueError(f"converter returned shapes {p_opt.shape}, {flags.shape} for {ci.shape}")
        return p_opt, flags, env_flags, rows, sigma

    def _ids(self, rows: list[Ready]) -> tuple:
        """The detector ids of a block's rows, module by module (kept per row layout: a batch repeats it)."""
        per = [r.ids for r in rows]
        hit = self._ids_cache.get(tuple(map(id, per)))
        # The rows' id tuples are the Environment's cached ones: the same objects batch after batch (checked,
        # as an id may be reused once its object is gone).
        if hit is not None and all(a is b for a, b in zip(hit[0], per)):
            return hit[1]
        ids = tuple(d for r in per for d in r)
        if len(self._ids_cache) >= 256:
            self._ids_cache.clear()
        self._ids_cache[tuple(map(id, per))] = (per, ids)
        return ids

    def _converted(self, ids, ci, cq, env, chunks: int = 1) -> tuple:
        """p_opt, flags and sigma_P (None unless published) of a block of ``chunks`` chunks: LOW_RESPONSIVITY
        flagged when the pipeline has a noise model, in the conversion's own pass unless sigma_P is published;
        the call's CPU in ``kernel_cpu_s``, the call and its chunks in ``kernel_calls`` and ``kernel_chunks``."""
        c0 = time.thread_time()
        try:
            return self._call(ids, ci, cq, env)
        finally:
            dt = time.thread_time() - c0
            with self._kernel_lock:
                self.kernel_cpu_s += dt
                self.kernel_calls += 1
                self.kernel_chunks += chunks

    def _call(self, ids, ci, cq, env) -> tuple:
        if self._noise is None or not self._sigma_p:
            out = (self.converter.convert(ids, ci, cq, env) if self._noise is None else
                   low_responsivity_block(self.converter, ids, ci, cq, env, self._noise))
            return np.asarray(out.p_opt_w, dtype=float), np.asarray(out.flags, dtype=fl.FLAG_DTYPE), None
        out = self.converter.convert(ids, ci, cq, env)
        u = sigma_p_block(self.converter, ids, ci, cq, env, out, self._noise)
        return np.asarray(u.p_opt_w, dtype=float), np.asarray(u.flags, dtype=fl.FLAG_DTYPE), u.sigma_p_w

    def _pool(self):
        """Threads for the parts of a large run beyond the first (made on first use)."""
        if self._executor is None:
            from concurrent.futures import ThreadPoolExecutor

            self._executor = ThreadPoolExecutor(max_workers=self._threads - 1, thread_name_prefix="convert")
        return self._executor

    def _one(self, r: Ready) -> Converted:
        chunk = r.chunk
        shape = chunk.counts_i.shape
        try:
            # The converter flags rows it has no parameters for (UNKNOWN_CHANNEL) itself.
            env = EnvironmentBlock(t_bath_k=r.t_bath, b_field_t=r.b_field, v_thev_v=r.v_bias, flags=r.env_flags)
            p_opt, flags, sigma = self._converted(r.ids, chunk.counts_i, chunk.counts_q, env)
            if p_opt.shape != shape or flags.shape != shape:
                raise ValueError(f"converter returned shapes {p_opt.shape}, {flags.shape} for {shape}")
        except Exception as exc:  # noqa: BLE001 - one bad block must not stop the stream
            p_opt = np.full(shape, np.nan)
            flags = np.full(shape, fl.INVALID_INPUT, dtype=fl.FLAG_DTYPE)
            sigma = np.full(shape, np.nan, dtype=np.float32) if self._sigma_p else None
            self.books.bad("convert_failed", f"{type(exc).__name__}: {exc}",
                           keys.counts_key(self.books.config.setup, chunk.board, chunk.module))
        return Converted(r, p_opt, flags, sigma)


class Flags:
    """Whatever the converter did: housekeeping and unknown-row flags hold, and flagged power is NaN.

    Applied once per converted block (then sliced into chunks), or per chunk
    converted alone. Books the flag counts and unknown-channel samples. Stale
    housekeeping (the last good reading older than its limit) makes power NaN
    when ``hk_stale_power = "nan"``. The first stage to see chunks one by one
    again, it puts a batch's chunks back in their release order (see ``_runs``).
    """

    name = "flags"
    takes, gives = (Run, Converted), (Flagged,)

    def __init__(self, books: Books):
        self.books = books
        nan_too = fl.HK_STALE if books.config.hk_stale_power == "nan" else 0
        self._unusable = fl.UNUSABLE | nan_too

    def __call__(self, items: list) -> list:
        out, done = [], []
        for item in items:
            kind = type(item)
            if kind is Run:
                self._run(item, done)
            elif kind is Converted:
                r = item.ready
                p, f, s = self.finish(item.p_opt, item.flags, r.env_flags, r.known if r.n_unknown else None,
                                      item.sigma)
                done.append(Flagged(r, p, f, s))
            else:
                self._in_order(done, out)
                out.append(item)
        self._in_order(done, out)
        return out

    @staticmethod
    def _in_order(done: list, out: list) -> None:
        """The converted chunks into ``out`` in their release order: each stream's in sequence (see ``_runs``)."""
        if done:
            done.sort(key=lambda c: c.ready.order)
            out += done
            done.clear()

    def _run(self, item: Run, out: list) -> None:
        run, cols = item.run, item.cols
        chunks: list[list] = [[None] * len(g) for g in run]
        for m0, m1, p_opt, flags, env_flags, rows, sigma in item.parts:
            known = np.concatenate([r.known for r in rows]) if any(r.n_unknown for r in rows) else None
            p_opt, flags, sigma = self.finish(p_opt, flags, env_flags, known, sigma)  # once for the block
            starts = np.cumsum([0] + [r.chunk.channels.size for r in rows])
            for g, order in enumerate(item.orders):
                c0, c1 = cols[g], cols[g + 1]
                for m in range(m0, m1):
                    r0, r1 = starts[m - m0], starts[m - m0 + 1]
                    chunks[g][order[m]] = Flagged(run[g][order[m]], p_opt[r0:r1, c0:c1], flags[r0:r1, c0:c1],
                                                  None if sigma is None else sigma[r0:r1, c0:c1])
        for row in chunks:
            out += row

    def finish(self, p_opt: np.ndarray, flags: np.ndarray, env_flags: np.ndarray, known: np.ndarray | None,
               sigma: np.ndarray | None = None):
        """p_opt, flags and sigma_P of a block with its flags completed; ``known``: rows with parameters (None: all)."""
        flags = flags | env_flags
        if known is not None:
            flags[~known] |= fl.UNKNOWN_CHANNEL
            self.books.counters.unknown_channel_samples += int((~known).sum()) * flags.shape[1]
        if flags.any():
            unusable = (flags & self._unusable) != 0
            if unusable.any():
                p_opt = np.where(unusable, np.nan, p_opt)
                if sigma is not None:
                    sigma = np.where(unusable, np.float32(np.nan), sigma)
            self.books.flag_counts.update(fl.counts_by_flag(flags))
        return p_opt, flags, sigma


class Encode:
    """Each converted chunk to its power message ``(key, payload)``, booked in the counters and the ledger.

    The payload comes from the stream's template (``io.lean.PowerEncoder``):
    byte-identical to ``PowerChunk.to_bytes``, from checked inputs, not checked again.
    """

    name = "encode"
    takes, gives = (Flagged,), (Output,)

    def __init__(self, books: Books, table_identity: str, kind: str, typed: bool = False):
        self.books = books
        self._encoder = PowerEncoder(books.config.setup, table_identity, kind)
        self._make = self._encoder.chunk if typed else self._encoder.encode  # typed: the PowerChunk, not its bytes
        self._keys: dict[tuple[int, int], str] = {}  # power key per stream (bounded by the known modules)
        self._hk_counts: tuple = (None, 0, 0)  # (a step's aligned flags, its stale samples, its missing samples)

    def __call__(self, items: list) -> list:
        out = []
        for item in items:
            if type(item) is not Flagged:
                out.append(item)
                continue
            try:
                out.append(self._one(item))
            except Exception as exc:  # noqa: BLE001
                self.books.dropped(item.ready.chunk, exc)
        return out

    def _one(self, item: Flagged) -> tuple[str, bytes]:
        r, books = item.ready, self.books
        chunk, cfg = r.chunk, books.config
        n_ch, n = chunk.counts_i.shape
        t_pub = books.stamp()
        payload = self._make(chunk, item.p_opt, item.flags, t_pub, r.late, item.sigma)
        stream = (chunk.board, chunk.module)
        books.ledger.done(stream, late=r.late)
        c = books.counters
        c.chunks_converted += 1
        c.samples_converted += n_ch * n
        hk = self._hk_counts
        if hk[0] is not r.env_flags_t:  # counted once per step: its modules share the (read-only) array
            f = r.env_flags_t
            hk = self._hk_counts = ((f, int(np.count_nonzero(f & fl.HK_STALE)),
                                     int(np.count_nonzero(f & fl.HK_MISSING))) if f.any() else (f, 0, 0))
        c.hk_stale_samples += hk[1]
        c.hk_missing_samples += hk[2]
        books.interval.add(n_ch * n, (t_pub - chunk.t_pub_ns) / 1e6)
        key = self._keys.get(stream)
        if key is None:
            key = self._keys[stream] = keys.power_key(cfg.setup, chunk.board, chunk.module)
        return key, payload

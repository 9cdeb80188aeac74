"""The array simulator writing G3 (``simulate --format g3``): MNTES physics, DfMux frames, truth alongside.

What a DfMux DAQ would have written for the simulated array: a Wiring frame
(bolometer ``Sim<board>.<module>.<channel>`` on board serial ``board``,
module 0-7, channel 0-indexed), DfMux housekeeping whose carrier amplitudes
give the simulated bias and whose nuller gain sets amps per count (spt3g's
own conversion functions), GcpSlow bath-temperature readings, and the
counts, either as raw Timepoint frames (``layout="timepoints"``, int32 as
the DfMux sends them) or as collated Scan frames (``layout="scans"``).

The counts of a sample are the simulated readout current over spt3g's gain:
``(I + jQ) = i / (sqrt(2) a(t) e^{j phi})`` with ``a(t)`` the RMS amps per
count of the housekeeping in force and ``phi`` the channel's demodulation
phase (the phase of the truth ``gain_a_per_count``). DfMux counts are
integers of ~5e-11 A, which alone limits the optical power to ~1e-17 W;
``exact_counts=True`` (scans only) writes the readout current itself over the
gain (float64 counts, no FLAC; not even the simulator's own 1 pA rounding)
so that a converter can be checked against the truth to 1e-19 W.

spt3g has no magnetic-field source, so the simulated field is zero.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mntes_stream.core import model
from mntes_stream.core.sim import ArraySimulator, SimConfig, solve_quasi_static
from mntes_stream.errors import ConfigError
from mntes_stream.g3.frames import ModuleHk, g3_time, gcpslow_frame, housekeeping_frame, timepoint_frame, wiring_frame
from mntes_stream.g3.mapping import SQRT2, Wiring, hk_snapshot
from mntes_stream.g3.runtime import spt3g

__all__ = ["write_g3", "bolometer_name", "G3_LAYOUTS", "g3_sim_config"]

G3_LAYOUTS = ("scans", "timepoints")
CARRIER_GAIN = 3


def bolometer_name(board: int, module: int, channel: int) -> str:
    return f"Sim{board}.{module}.{channel:03d}"


def g3_sim_config(config: SimConfig) -> SimConfig:
    """``config`` with the magnetic field off (G3 has no field source) and a DfMux-sized array checked."""
    if config.modules > 8:
        raise ConfigError("G3 simulation: at most 8 modules per board (2 mezzanines x 4)")
    return config.replace(b_field_t=0.0, b_field_offset_t=0.0, b_field_amp_t=0.0, b_field_fluct_t=0.0,
                          b_field_ramp_t_per_s=0.0)


def _module_hk(config: SimConfig, amplitude: np.ndarray, nuller_gain: int, wiring: Wiring, freq: np.ndarray) -> dict:
    out: dict = {}
    for (b, m), rows in wiring.modules().items():
        out.setdefault(int(b), {})[int(m)] = ModuleHk(nuller_gain, CARRIER_GAIN, amplitude[rows], freq[rows])
    return out


def write_g3(config: SimConfig, path, duration_s: float, *, layout: str = "scans", t0_ns: int | None = None,
             truth=None, exact_counts: bool = False, nuller_gain: int = 2, gain_steps=(), block_samples: int = 0,
             params_out=None) -> dict:
    """Simulate ``duration_s`` of the array into a G3 file.

    Parameters
    ----------
    config : SimConfig
    path : path
        The G3 file (not overwritten).
    layout : {"scans", "timepoints"}
    truth : TruthRecorder, optional
        Receives every simulated block.
    exact_counts : bool
        Scans only: unrounded float64 counts (for checks against the truth).
    nuller_gain : int
        DfMux nuller gain at the start (0-15).
    gain_steps : sequence of (time s, nuller gain)
        The operator changes the nuller gain: a Housekeeping frame at that time, and counts after it in the new
        amps per count.
    block_samples : int
        Samples per Scan frame (default: 1 s).
    params_out : path, optional
        The truth parameters keyed by bolometer name.
    """
    core, dfmux = spt3g()
    if layout not in G3_LAYOUTS:
        raise ConfigError(f"G3 layout must be one of {G3_LAYOUTS}, got {layout!r}")
    if exact_counts and layout != "scans":
        raise ConfigError("exact (unrounded) counts only fit the scans layout: DfMux Timepoints are int32")
    path = Path(path)
    if path.exists():
        raise ConfigError(f"{path} exists: not overwritten")
    config = g3_sim_config(config)
    import time as _time

    t0 = int(t0_ns if t0_ns is not None else _time.time_ns())
    t0 -= t0 % 10  # G3 ticks are 10 ns
    sim = ArraySimulator(config, t0_ns=t0)
    n_total = max(1, int(round(duration_s * config.sample_rate_hz)))
    block = int(block_samples or max(1, round(config.sample_rate_hz)))
    chans = sim.channels
    layout_map = {bolometer_name(ch.board, ch.module, ch.channel): (ch.board, ch.module, ch.channel) for ch in chans}
    wf = wiring_frame(layout_map)
    wiring = Wiring.from_frame(wf)
    name_of = dict(zip(wiring.detector_ids, wiring.names))
    order = np.array([wiring._by_id[d] for d in sim.detector_ids])  # sim row -> wiring row
    freq = np.empty(len(wiring))
    freq[order] = 1.6e6 + 4e4 * np.array([ch.channel for ch in chans]) + 1e3 * np.array([ch.module for ch in chans])
    ones = np.ones(len(wiring))
    gains = sorted({int(nuller_gain), *(int(g) for _, g in gain_steps)})
    unit = {g: hk_snapshot(housekeeping_frame(t0, _module_hk(config, ones, g, wiring, freq))["DfMuxHousekeeping"],
                           wiring) for g in gains}
    volts_per_amp = unit[gains[0]].v_bias_rms_v  # the carrier chain: independent of the nuller gain
    v_set = np.empty(len(wiring))
    v_set[order] = sim._v_set[:, 0]
    gain_sim = np.asarray(sim._pa.gain_a_per_count)[:, 0]  # (n_det,) complex, sim order
    steps = sorted((t0 + int(round(t_s * 1e9)), int(g)) for t_s, g in gain_steps)

    def gain_at(t_ns):
        g = np.full(np.shape(t_ns), int(nuller_gain))
        for t_step, gs in steps:
            g[np.asarray(t_ns) >= t_step] = gs
        return g

    def hk_frame(t_ns, g):
        amp = v_set * float(sim.bias_factor(np.array([t_ns]))[0]) / volts_per_amp
        return housekeeping_frame(t_ns, _module_hk(config, amp, g, wiring, freq))

    if params_out is not None:
        from mntes_stream.io.paramfile import dump_params

        dump_params([p.replace(detector_id=name_of[p.detector_id]) for p in sim.truth_params], params_out,
                    metadata={"source": "mntes-stream simulate --format g3 (truth, keyed by bolometer name)"})

    def frames():
        yield wf
        yield hk_frame(t0 - 10, int(nuller_gain))
        # The thermometer is read at the start and the end too (a converter interpolates between readings).
        yield gcpslow_frame(t0, float(sim.t_bath_k(np.array([0.0]))[0]))
        done = 0
        t_end = t0
        step_queue = list(steps)
        while done < n_total:
            blk = sim.next_block(min(block, n_total - done))
            if truth is not None:
                truth.add(blk)
            t_end = int(blk.t_ns[-1])
            for h in blk.hk:
                if h.sensor == "t_bath":
                    for t, v in zip(h.t_ns, h.value):
                        yield gcpslow_frame(int(t), float(v))
            hk_times = {int(t) for h in blk.hk if h.sensor == "bias" for t in h.t_ns}
            while step_queue and step_queue[0][0] <= t_end:
                hk_times.add(step_queue.pop(0)[0])
            for t in sorted(hk_times):
                yield hk_frame(t, int(gain_at(np.array([t]))[0]))
            g_samp = gain_at(blk.t_ns)  # (n_samp,)
            a = np.stack([unit[g].amps_rms_per_count[order] for g in g_samp], axis=1)  # (n_det, n_samp), sim order
            if exact_counts:  # the readout current itself, not the simulator's counts rounded at its own gain
                b_row = blk.truth_b_field_t[None, :]
                op = solve_quasi_static(sim._pa, blk.truth_p_opt_w, blk.truth_t_bath_k[None, :], b_row,
                                        blk.truth_v_thev_v)
                c = model.readout_current_a(sim._pa, op.i_a, b_row) / (SQRT2 * a * (gain_sim / np.abs(gain_sim))[:, None])
                ci, cq = c.real, c.imag
            else:
                scale = np.abs(gain_sim)[:, None] / (SQRT2 * a)
                ci, cq = blk.counts_i * scale, blk.counts_q * scale
            if layout == "scans" and exact_counts:
                names = [name_of[d] for d in sim.detector_ids]
                start, stop = g3_time(blk.t_ns[0]), g3_time(blk.t_ns[-1])
                f = core.G3Frame(core.G3FrameType.Scan)
                f["RawTimestreams_I"] = core.G3TimestreamMap(names, ci, start, stop, core.G3TimestreamUnits.Counts)
                f["RawTimestreams_Q"] = core.G3TimestreamMap(names, cq, start, stop, core.G3TimestreamUnits.Counts)
                f["DetectorSampleTimes"] = core.G3VectorTime([g3_time(t) for t in blk.t_ns])
                yield f
            else:
                ci, cq = np.rint(ci).astype(np.int32), np.rint(cq).astype(np.int32)
                if layout == "scans":
                    yield core.G3Frame(core.G3FrameType.Scan)  # DfMuxCollator: a scan starts here
                for k, t in enumerate(blk.t_ns):
                    samples = {}
                    for b in range(config.boards):
                        for m in range(config.modules):
                            rows = sim.module_rows(b, m)
                            samples[(b, m)] = (ci[rows, k], cq[rows, k])
                    yield timepoint_frame(int(t), samples, config.channels)
            done += blk.n_samples
        yield gcpslow_frame(t_end, float(sim.t_bath_k(np.array([(t_end - t0) * 1e-9]))[0]))

    gen = frames()
    state = {"done": False}

    def source(_frame):
        if state["done"] or writer.error is not None:
            return []
        try:
            return [next(gen)]
        except StopIteration:
            state["done"] = True
            return []

    from mntes_stream.g3.wire import AtomicG3Writer

    with AtomicG3Writer(path, defer_errors=True) as writer:  # under its name only when complete
        pipe = core.G3Pipeline()
        pipe.Add(source)
        if layout == "scans" and not exact_counts:
            pipe.Add(dfmux.DfMuxCollator, flac_compress=True)
        pipe.Add(writer)
        pipe.Run()
    return {"output": str(path), "layout": layout, "samples": n_total, "detectors": config.n_detectors,
            "exact_counts": exact_counts, "first_sample_ns": t0}

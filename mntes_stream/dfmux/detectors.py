"""The detectors behind a synthetic IceBoard: the array simulator's, with their bias, at the DfMux rate.

A :class:`DetectorBoard` is one board serial's :class:`~mntes_stream.core.sim.ArraySimulator`
(``modules`` x ``channels``, seeded by ``(seed, serial)``), its detectors named
``b<serial>m<module>c<channel>`` as ``dfmux-bridge`` publishes them. What
differs from the simulator's defaults (:func:`board_config`), so that what the
bridge publishes is what these detectors saw:

- one RMS bias per module (``bias_per_module``: the median of its channels'
  tuned biases), since the bridge's bias table is per module;
  :attr:`DetectorBoard.bias_v` states it, :meth:`DetectorBoard.bias_args` gives
  it as the bridge's ``--bias`` entries;
- a steady environment, the one the bridge's settings state: bath at
  ``T_BATH_K``, field 0, no bias step (no wander or fluctuation);
- no latched channel: its quarter bias cannot be said in a per-module table.
  One channel per module is saturated (loading 3 x P_sat: normal), as in the
  simulator.

The optical signal (loading, HWP 2f, dipole, Jupiter crossings), photon and
readout noise are the simulator's. Counts are its int32 ``I / gain`` (the
converter's convention, ``core.params``), pinned to the board's 24-bit word
(packets carry them x 256).
"""

from __future__ import annotations

import numpy as np

from mntes_stream.core.ids import detector_id
from mntes_stream.core.params import DetectorParams
from mntes_stream.core.sim import ArraySimulator, SimConfig
from mntes_stream.core.timing import DFMUX_SAMPLE_RATE_HZ

__all__ = ["DetectorBoard", "board_config", "T_BATH_K", "COUNTS_MAX"]

T_BATH_K = 0.1
COUNTS_MAX = 2**23 - 1  # a board's samples are 24-bit words (the collector divides the packet's int32 by 256)


def board_config(serial: int, modules: int, channels: int, seed: int = 0, **changes) -> SimConfig:
    """The simulator's configuration of one board's detectors (see the module's docstring).

    ``changes``: any other :class:`~mntes_stream.core.sim.SimConfig` field.
    """
    base = dict(boards=1, modules=int(modules), channels=int(channels), seed=(int(seed) << 16) | int(serial),
                sample_rate_hz=DFMUX_SAMPLE_RATE_HZ, bias_per_module=True, latched_per_module=0,
                saturated_per_module=1 if channels > 1 else 0, bias_steps=(), t_bath_k=T_BATH_K,
                t_bath_wander_k=0.0, t_bath_fluct_k=0.0, b_field_t=0.0, b_field_amp_t=0.0, b_field_fluct_t=0.0)
    base.update(changes)
    return SimConfig(**base)


class DetectorBoard:
    """The simulated detectors of one board, block by block.

    Parameters
    ----------
    serial : int
        Board serial: the detector ids are ``b<serial>m<module>c<channel>``.
    modules, channels : int
        Modules on the board and channels per module.
    seed : int
        With the serial, the simulator's seed: the same arguments give the same detectors.
    t0_ns : int
        Time of sample 0 (the simulator's; the optical signal is a function of the sample number).
    **changes
        Other :class:`~mntes_stream.core.sim.SimConfig` fields (:func:`board_config`).

    Attributes
    ----------
    sim : ArraySimulator
    params : tuple of DetectorParams
        The truth, ids as the bridge publishes them (a converter's parameter file).
    bias_v : ndarray, shape (modules,)
        RMS Thevenin bias of each module, V (every channel of a module has it).
    """

    def __init__(self, serial: int, modules: int, channels: int, seed: int = 0, t0_ns: int = 0, **changes):
        self.serial, self.modules, self.channels = int(serial), int(modules), int(channels)
        self.config = board_config(serial, modules, channels, seed, **changes)
        self.sim = ArraySimulator(self.config, t0_ns)
        self.params: tuple[DetectorParams, ...] = tuple(
            p.replace(detector_id=detector_id(self.serial, ch.module, ch.channel))
            for p, ch in zip(self.sim.truth_params, self.sim.channels))
        v = np.array([p.v_thev_v for p in self.params]).reshape(self.modules, self.channels)
        self.bias_v = v[:, 0].copy()

    def bias_args(self) -> list[str]:
        """``dfmux-bridge`` arguments publishing this board's bias: ``--bias SERIAL/MODULE=VOLTS`` per module."""
        return [a for m, v in enumerate(self.bias_v) for a in ("--bias", f"{self.serial}/{m}={float(v)!r}")]

    def next_counts(self, n: int):
        """The next ``n`` samples: ``(block, I, Q)``, I and Q int32 of shape (modules, channels, n).

        ``block`` is the simulator's :class:`~mntes_stream.core.sim.SimBlock` (its ``truth_`` fields).
        """
        blk = self.sim.next_block(n)
        shape = (self.modules, self.channels, blk.n_samples)
        ci, cq = (np.clip(c, -COUNTS_MAX, COUNTS_MAX).reshape(shape) for c in (blk.counts_i, blk.counts_q))
        return blk, ci, cq

"""The housekeeping the DfMux bridge publishes beside its counts: as the simulator does, from configuration.

``t_bath`` and ``b_field`` (constants, when configured) with every group of
counts chunks, stamped at the newest sample, so the converter never waits
for a reading after a chunk; ``bias/<board>/<module>`` (RMS volts, from the
configured table) when a module is first seen and every ``bias_every_s``
of data time after.
"""

from __future__ import annotations

import numpy as np

from mntes_stream.io import keys
from mntes_stream.io.messages import HousekeepingChunk

__all__ = ["HkPublisher"]


class HkPublisher:
    """Housekeeping messages to go out before a group of counts chunks.

    Parameters
    ----------
    setup : str
    t_bath_k, b_field_t : float or None
        Constants to publish (None: not published here).
    bias : list of (board or None, module or None, volts)
        The bias table, first match wins (:func:`~mntes_stream.dfmux.bridge.bias_table`).
    bias_every_s : float
    """

    def __init__(self, setup: str, t_bath_k, b_field_t, bias, bias_every_s: float = 60.0):
        self.setup = setup
        self.scalars = [(s, v, u) for s, v, u in (("t_bath", t_bath_k, "K"), ("b_field", b_field_t, "T"))
                        if v is not None]
        self.bias = list(bias)
        self.bias_every_ns = int(bias_every_s * 1e9)
        self._seq: dict[str, int] = {}
        self._t_scalar = -1
        self._t_bias: dict[tuple[int, int], int] = {}
        self.readings = 0

    def _bias_of(self, board: int, module: int) -> float | None:
        for b, m, v in self.bias:
            if (b is None or b == board) and (m is None or m == module):
                return v
        return None

    def _msg(self, sensor: str, t_ns: int, value, unit: str, **where) -> tuple[str, bytes]:
        sk = keys.hk_sensor(sensor, where.get("board"), where.get("module"))
        seq = self._seq.get(sk, 0)
        self._seq[sk] = seq + 1
        self.readings += 1
        msg = HousekeepingChunk(setup=self.setup, sensor=sensor, seq=seq, t_ns=np.array([t_ns], dtype=np.int64),
                                value=np.asarray(value, dtype=float), unit=unit, **where)
        return keys.hk_key(self.setup, sk), msg.to_bytes()

    def messages(self, chunks, t_newest_ns: int) -> list[tuple[str, bytes]]:
        """What to publish before ``chunks`` (counts chunks just completed)."""
        if not chunks:
            return []
        t = max(t_newest_ns, max(int(c.t_ns[-1]) for c in chunks))
        out = []
        if t > self._t_scalar:
            self._t_scalar = t
            out += [self._msg(s, t, [v], u) for s, v, u in self.scalars]
        for c in chunks:
            key = (c.board, c.module)
            last = self._t_bias.get(key)
            if last is not None and t - last < self.bias_every_ns:
                continue
            v = self._bias_of(c.board, c.module)
            if v is None:
                continue
            self._t_bias[key] = t
            n = c.channels.size
            out.append(self._msg("bias", t, np.full((1, n), v), "V", board=c.board, module=c.module,
                                 channels=c.channels))
        return out

"""The housekeeping the DfMux bridge publishes beside its counts.

``t_bath`` and ``b_field`` (constants, when configured) with every group of
counts chunks, stamped at the newest sample, so the converter never waits
for a reading after a chunk. ``bias/<board>/<module>`` (RMS volts): the
board's own (:mod:`.boardhk`, :meth:`HkPublisher.board_bias`) once it has
been read; until then, from the configured table, when a module is first
seen and every ``bias_every_s`` of data time after. ``readout_flags/<board>/
<module>``: the board's per-channel flags (:meth:`HkPublisher.board_flags`).
Per module, readings go out in time order: a board reading stamped before
the module's last published one is moved just after it.
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
        self._t_sent: dict[str, int] = {}  # per-channel sensor key -> its last reading's time
        self.from_board: set[tuple[int, int]] = set()
        self.readings = 0

    def configured_bias(self, board: int, module: int) -> float | None:
        """The bias table's value for a module (None: no entry)."""
        return self._bias_of(board, module)

    def board_bias(self, board: int, module: int, channels, t_ns, volts) -> list[tuple[str, bytes]]:
        """The board's bias readings of a module (``t_ns`` shape (n,), ``volts`` (n, n_ch)); from now on the
        table is not used for it."""
        self.from_board.add((board, module))
        return [self._msg("bias", t_ns, volts, "V", board=board, module=module, channels=channels)]

    def board_flags(self, board: int, module: int, channels, t_ns: int, flags) -> list[tuple[str, bytes]]:
        """The board's readout flags of a module's channels, from ``t_ns`` on."""
        return [self._msg("readout_flags", [t_ns], np.asarray(flags, dtype=float)[None, :], "flags", board=board,
                          module=module, channels=channels)]

    def _bias_of(self, board: int, module: int) -> float | None:
        for b, m, v in self.bias:
            if (b is None or b == board) and (m is None or m == module):
                return v
        return None

    def _msg(self, sensor: str, t_ns, value, unit: str, **where) -> tuple[str, bytes]:
        sk = keys.hk_sensor(sensor, where.get("board"), where.get("module"))
        seq = self._seq.get(sk, 0)
        self._seq[sk] = seq + 1
        t = np.atleast_1d(np.asarray(t_ns, dtype=np.int64))
        if "channels" in where:  # in time order per module: after the last reading sent (a table's, say)
            t = t + max(0, self._t_sent.get(sk, -1) + 1 - int(t[0]))
            self._t_sent[sk] = int(t[-1])
        self.readings += t.size
        msg = HousekeepingChunk(setup=self.setup, sensor=sensor, seq=seq, t_ns=t,
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
            if key in self.from_board:
                continue
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

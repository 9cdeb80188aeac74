"""One runner for every driver of the converter: batching, ticks, late power, flush, calibration switches.

The drivers are small adapters around it: the converter service hands it
what its subscriber received (:meth:`Runner.feed_batch`, :meth:`Runner.idle`
when nothing came), offline ``convert`` each recorded message
(:meth:`Runner.feed`: batched by receive time, the calibration switched at its
recorded times), the G3 ``OpticalPower`` module each frame's messages. Every
output is ``(key, payload, t_ns)``: a message and the receive time it is
written at (offline: its log time).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

from mntes_stream.io import keys
from mntes_stream.pipeline.pipeline import ConverterPipeline

__all__ = ["Runner"]


def _at(outs: list, t_ns) -> list[tuple]:
    return [(k, p, t_ns) for k, p in outs]


class Runner:
    """Feeds :class:`~mntes_stream.pipeline.pipeline.ConverterPipeline` (one per calibration) and gathers its outputs.

    Parameters
    ----------
    start : callable ``start(k) -> ConverterPipeline``
        The pipeline of calibration ``k`` (0, 1, ...), started at the first message or at its switch.
    switches : sequence of int
        Receive times (ns, increasing) at which calibration ``k + 1`` takes over from ``k``: what the
        old pipeline holds arrived before, so it is the old one's to convert (a tick to the switch, a
        flush), as the stopped live converter did; the new one starts at the switch.
    batch_s : float
        :meth:`feed`: > 0, the messages of each ``batch_s`` of receive time (and at most ``batch_bytes``
        of payload) go through the pipeline together, their outputs written at the batch's last
        message; 0, message by message, a tick before each (what waited long enough before it is released
        first, as the live service's ticks do).
    batch_bytes : int
    inputs : bool
        :meth:`feed` gives each message back among the outputs, where it belongs in the order of writing.
    provenance : bool
        Each pipeline's provenance is an output when it starts.
    retire : callable ``retire(pipeline)``, optional
        Called with each pipeline once it has been flushed (its final figures).
    """

    def __init__(self, start: Callable[[int], ConverterPipeline], *, switches: Sequence[int] = (),
                 batch_s: float = 0.0, batch_bytes: int = 64 << 20, inputs: bool = False, provenance: bool = False,
                 retire: Callable[[ConverterPipeline], None] | None = None):
        self._start, self._switches = start, [int(t) for t in switches]
        self.batch_s, self.batch_bytes = float(batch_s), int(batch_bytes)
        self._inputs, self._provenance, self._retire = inputs, provenance, retire
        self.pipe: ConverterPipeline | None = None
        self.epoch = 0  # the calibration in force
        self.t_last_ns: int | None = None
        self._batch: list = []
        self._bytes = 0

    @classmethod
    def around(cls, pipe: ConverterPipeline) -> Runner:
        """A runner of one ready pipeline (the live service, the G3 module)."""
        runner = cls(lambda k: pipe)
        runner.pipe = pipe
        return runner

    # ------------------------------------------------------------------ a message at a time (offline)

    def feed(self, key: str, payload: bytes, t_ns: int) -> list[tuple]:
        """One received message; the outputs due now (with the message itself first, given ``inputs``)."""
        out = self._switch(t_ns)
        self.t_last_ns = t_ns
        if self.batch_s > 0:
            if self._inputs:
                out.append((key, payload, t_ns))
            if self._batch and (t_ns - self._batch[0][2] > self.batch_s * 1e9 or self._bytes > self.batch_bytes):
                out += self._run_batch()
            self._batch.append((key, payload, t_ns))
            self._bytes += len(payload)
        else:
            out += _at(self.pipe.tick(t_ns), t_ns)
            if self._inputs:
                out.append((key, payload, t_ns))
            out += _at(self.pipe.handle(key, payload, t_ns), t_ns)
        return out

    def _begin(self, k: int, t_ns: int) -> list[tuple]:
        self.pipe = self._start(k)
        if not self._provenance:
            return []
        return [(keys.provenance_key(self.pipe.config.setup), self.pipe.provenance_bytes(), t_ns)]

    def _switch(self, t_ns: int) -> list[tuple]:
        """Start the first pipeline, or switch the calibration when ``t_ns`` passed its switch."""
        n = len(self._switches)
        if self.pipe is not None and not (self.epoch < n and t_ns >= self._switches[self.epoch]):
            return []
        while self.epoch < n and t_ns >= self._switches[self.epoch]:
            self.epoch += 1
        if self.pipe is None:
            return self._begin(self.epoch, t_ns)
        t_switch = self._switches[self.epoch - 1]
        out = self._run_batch() + _at(self.pipe.tick(t_switch), t_switch) + _at(self.pipe.flush(), t_switch)
        if self._retire is not None:
            self._retire(self.pipe)
        return out + self._begin(self.epoch, t_switch)

    def _run_batch(self) -> list[tuple]:
        if not self._batch:
            return []
        batch, self._batch, self._bytes = self._batch, [], 0
        return _at(self.pipe.handle_many(batch), batch[-1][2])

    # ------------------------------------------------------------------ batches a driver made (live, G3)

    def feed_batch(self, items, t_ns: int | None = None) -> list[tuple]:
        """Received ``(key, payload, t_recv_ns[, source])`` items as one batch (``handle_many``); outputs at ``t_ns``."""
        return _at(self.pipe.handle_many(items), t_ns)

    def idle(self, t_ns: int, late_chunks: int = 0) -> list[tuple]:
        """Nothing received: time passes (chunks that waited long enough released, a status when due), then
        up to ``late_chunks`` set-aside chunks converted (late power)."""
        return _at(self.pipe.tick(t_ns) + self.pipe.convert_late(late_chunks), t_ns)

    def finish(self) -> list[tuple]:
        """What is batched, then everything held, converted; the final status. The pipeline is retired."""
        if self.pipe is None:
            return []
        out = self._run_batch() + _at(self.pipe.flush(), self.t_last_ns)
        if self._retire is not None:
            self._retire(self.pipe)
        return out

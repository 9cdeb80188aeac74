"""The monitor's linear shadow: the linear baseline of the counts of the detectors it measures.

For the live leakage (``monitor/leakage_live.py``) the monitor needs, next to
the converter's MNTES power, the power the linear conversion gives from the
same counts. It converts them itself with the converter's own code: a
:class:`~mntes_stream.pipeline.pipeline.ConverterPipeline` of kind ``linear``
(``core.convert.LinearConverter``) built for the measured detectors only,
fed the counts of their modules and every housekeeping message, exactly as
the converter is fed. The parameters come from the converter's provenance
(``mntes/<setup>/provenance``, republished every 10 s; merged over shards),
or from the monitor's ``params`` file when one is given. No ``NONLINEAR``
check (``tolerance_w = None``): the flag does not change the power, and the
check would build a table bank. Alignment settings are the pipeline's
defaults (a converter run with others may flag some samples differently;
the leakage fit only uses samples both conversions give).
"""

from __future__ import annotations

import hashlib
import logging
import time
import tomllib

from mntes_stream.errors import ConfigError, SchemaError
from mntes_stream.io import keys
from mntes_stream.io.messages import PowerChunk

__all__ = ["LinearShadow"]

log = logging.getLogger("mntes_stream.monitor")


class LinearShadow:
    """Counts + housekeeping in, the linear baseline's power chunks out, for ``detector_ids`` only.

    Parameters
    ----------
    setup : str
    detector_ids : list of str
        The measured detectors (``LiveLeakage.chosen``).
    """

    def __init__(self, setup: str, detector_ids):
        self.setup = setup
        self.detector_ids = list(detector_ids)
        self.params: dict = {}
        self.pipeline = None
        self.no_baseline: set[str] = set()
        self.state = "waiting for the converter's provenance (parameters)"
        self._seen: set[bytes] = set()
        self.chunks_out = 0

    def add_params(self, pdict: dict) -> bool:
        """Parameters (id -> DetectorParams) of some detectors; True when the shadow needs a (re)build."""
        new = {d: q for d, q in pdict.items() if d in self.detector_ids and d not in self.params}
        self.params.update(new)
        return bool(new)

    def add_params_toml(self, text: str, source: str) -> bool:
        """:meth:`add_params` from a parameter TOML (a provenance's ``params_toml``); each text parsed once."""
        from mntes_stream.io.paramfile import parse_params

        digest = hashlib.sha256(text.encode()).digest()
        if digest in self._seen:
            return False
        if len(self._seen) >= 256:  # shards' texts, each republished every 10 s: a few in practice
            self._seen.clear()
        self._seen.add(digest)
        try:
            return self.add_params(parse_params(tomllib.loads(text), source))
        except (tomllib.TOMLDecodeError, ConfigError) as exc:
            self.state = f"parameters unreadable ({source}): {exc}"[:300]
            return False

    def build(self) -> None:
        """The pipeline for the measured detectors whose parameters are known and that a baseline can take."""
        from mntes_stream.core.convert import baseline_can_take, make_converter
        from mntes_stream.pipeline import ConverterPipeline, PipelineConfig

        usable = {d: q for d, q in self.params.items() if baseline_can_take(q)}
        self.no_baseline = {d for d in self.params if d not in usable}
        if not usable:
            self.state = "no measured detector has a linear baseline (latched or normal at its nominal point)"
            return
        t0 = time.monotonic()
        conv = make_converter("linear", usable, tolerance_w=None)
        self.pipeline = ConverterPipeline(conv, PipelineConfig(setup=self.setup, service="monitor-shadow"), clock=None)
        self.state = f"linear shadow of {len(usable)} detectors"
        log.info("monitor: %s built in %.2f s", self.state, time.monotonic() - t0)

    def _power(self, out) -> list[PowerChunk]:
        chunks = []
        for key, payload in out:
            if keys.kind_of(key) != "power":
                continue
            try:
                chunks.append(PowerChunk.from_bytes(payload))
            except SchemaError:  # our own encoding: a bug, not the peer's
                log.exception("monitor: linear shadow produced an undecodable power chunk")
        self.chunks_out += len(chunks)
        return chunks

    def handle(self, key: str, payload: bytes, t_recv_ns: int) -> list[PowerChunk]:
        """One counts or housekeeping message; the linear power chunks released by it."""
        if self.pipeline is None:
            return []
        return self._power(self.pipeline.handle(key, payload, t_recv_ns))

    def tick(self, t_now_ns: int) -> list[PowerChunk]:
        """Let time pass: chunks that waited ``hk_wait_s`` for housekeeping are converted."""
        if self.pipeline is None:
            return []
        return self._power(self.pipeline.tick(t_now_ns))

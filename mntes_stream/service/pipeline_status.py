"""The converter pipeline's reports: its status (interval figures, the ledger) and its provenance.

A mixin of :class:`~mntes_stream.service.pipeline.ConverterPipeline` (its
counters, ledger, streams and config), kept apart so each module stays one concern.
"""

from __future__ import annotations

import time

import numpy as np

from mntes_stream import __version__
from mntes_stream.core import flags as fl
from mntes_stream.io import keys
from mntes_stream.io.messages import Provenance, StatusMessage

__all__ = ["Reporting"]


class Reporting:
    """Status and provenance messages of the pipeline (see the module docstring)."""

    def status(self) -> StatusMessage:
        """The status as of the latest message (interval figures since the last emitted status)."""
        now = self._now_ns if self._now_ns is not None else time.time_ns()
        start = self._t_first_ns if self._t_first_ns is not None else now
        since = self._last_status_ns if self._last_status_ns is not None else start
        interval_s = max(now - since, 0) / 1e9
        lat = np.asarray(self._interval_latency_ms)
        c = self.counters
        streams = self._streams.values()
        led = self.ledger_now()
        tot = led.totals()
        return StatusMessage(
            setup=self.config.setup,
            service=self.config.service,
            t_ns=max(now, 0),
            uptime_s=max(now - start, 0) / 1e9,
            interval_s=interval_s,
            chunks_received=c.chunks_received,
            chunks_converted=c.chunks_converted,
            chunks_pending=len(self._pending),
            samples_converted=c.samples_converted,
            chunks_lost=tot.lost,
            chunks_missing=tot.missing,
            chunks_shed=tot.shed_total,
            chunks_late=tot.late,
            chunks_rejected=tot.rejected_total,
            chunks_set_aside=len(self._aside),
            ledger=led.as_dict(),
            chunks_duplicated=sum(s.duplicated for s in streams),
            chunks_out_of_order=sum(s.out_of_order for s in streams),
            hk_received=c.hk_received,
            hk_stale_samples=c.hk_stale_samples,
            hk_missing_samples=c.hk_missing_samples,
            unknown_channel_samples=c.unknown_channel_samples,
            bad_messages=dict(self.bad_messages),
            flag_counts={name: self.flag_counts.get(name, 0) for name in fl.NAMES.values()},
            hk_age_s=self.hk.ages_s(now),
            rate_chunks_per_s=self._interval_chunks / interval_s if interval_s > 0 else 0.0,
            rate_msamples_per_s=self._interval_samples / interval_s / 1e6 if interval_s > 0 else 0.0,
            latency_p50_ms=float(np.percentile(lat, 50)) if lat.size else None,
            latency_p99_ms=float(np.percentile(lat, 99)) if lat.size else None,
            latency_max_ms=float(lat.max()) if lat.size else None,
            last_error=self.last_error,
            owns=self.owns_status() if self.owns_status is not None else self._owns,
        )

    def provenance(self) -> Provenance:
        """Parameters (TOML text), table identity, converter kind and software version."""
        from mntes_stream.io.paramfile import params_to_toml

        return Provenance(
            setup=self.config.setup,
            params_toml=params_to_toml(self._params) if self._params else "",
            table_identity=str(self.converter.identity),
            converter_kind=str(self.converter.kind),
            software_version=__version__,
            t_ns=self._t_created_ns,
            owns=self._owns,
            noise=self._noise.provenance() if self._noise is not None else {},
        )

    def provenance_bytes(self) -> bytes:
        """:meth:`provenance` encoded once: identical bytes on every publication."""
        if self._provenance is None:
            self._provenance = self.provenance().to_bytes()
        return self._provenance

    def _maybe_status(self, out: list) -> None:
        if self._now_ns is not None and self._now_ns >= self._next_status_ns:
            out.append(self._emit_status())
            # Skip missed slots rather than bursting after a pause.
            while self._next_status_ns <= self._now_ns:
                self._next_status_ns += self._status_ns

    def _emit_status(self) -> tuple[str, bytes]:
        msg = self.status()
        self._last_status_ns = self._now_ns
        self._interval_latency_ms = []
        self._interval_chunks = 0
        self._interval_samples = 0
        return keys.status_key(self.config.setup, self.config.service), msg.to_bytes()

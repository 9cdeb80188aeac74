"""The converter's last stage: its status (interval figures, the ledger) and its provenance (no I/O)."""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np

from mntes_stream import __version__
from mntes_stream.core import flags as fl
from mntes_stream.core.shards import StreamKey
from mntes_stream.io import keys
from mntes_stream.io.messages import Provenance, StatusMessage
from mntes_stream.pipeline.housekeeping import ns
from mntes_stream.pipeline.items import End, Output
from mntes_stream.pipeline.stages import Align, Books, Sequence

__all__ = ["Status"]


class Status:
    """At the end of a batch, the status message when one is due (every ``status_interval_s`` of receive time).

    Parameters
    ----------
    books : Books
    sequence, align : the stages whose state the status reports (streams, set aside, held, housekeeping)
    converter, params, owns : what the provenance names
    params_toml : str, optional
        ``params`` as TOML text when the caller has it; default: written once, when first needed
    noise : callable returning the noise model in use (``core.uncertainty.NoiseModel``), or None
    """

    name = "status"
    takes, gives = (), (Output,)

    def __init__(self, books: Books, sequence: Sequence, align: Align, converter, params: list, owns: dict,
                 noise=None, sigma_p: bool = False, params_toml: str | None = None):
        self.books, self.sequence, self.align = books, sequence, align
        self._sigma_p = sigma_p
        self.converter, self._params, self._owns, self._noise = converter, params, owns, noise
        self._params_toml = params_toml
        self.owns_status: Callable[[], dict] | None = None
        self._status_ns = ns(books.config.status_interval_s)
        self._next_ns: int | None = None
        self._last_ns: int | None = None
        self._provenance: bytes | None = None
        self._provenance_noise = None
        self._t_created_ns = time.time_ns()

    def __call__(self, items: list) -> list:
        if items and type(items[-1]) is End:
            books = self.books
            if books.now_ns is not None:
                if self._next_ns is None:
                    self._last_ns = books.t_first_ns
                    self._next_ns = books.t_first_ns + self._status_ns
                if books.now_ns >= self._next_ns:
                    items.insert(len(items) - 1, self.emit())
                    # Skip missed slots rather than bursting after a pause.
                    while self._next_ns <= books.now_ns:
                        self._next_ns += self._status_ns
        return items

    def status(self) -> StatusMessage:
        """The status as of the latest message (interval figures since the last emitted status)."""
        books, seq = self.books, self.sequence
        now = books.now_ns if books.now_ns is not None else time.time_ns()
        start = books.t_first_ns if books.t_first_ns is not None else now
        since = self._last_ns if self._last_ns is not None else start
        interval_s = max(now - since, 0) / 1e9
        iv = books.interval
        lat, arr = np.asarray(iv.latency_ms), np.asarray(iv.arrival_ms)
        c = books.counters
        streams = seq.streams.values()
        led = seq.ledger_now()
        tot = led.totals()
        return StatusMessage(
            setup=books.config.setup,
            service=books.config.service,
            t_ns=max(now, 0),
            uptime_s=max(now - start, 0) / 1e9,
            interval_s=interval_s,
            chunks_received=c.chunks_received,
            chunks_converted=c.chunks_converted,
            chunks_pending=len(self.align.pending),
            samples_converted=c.samples_converted,
            chunks_lost=tot.lost,
            chunks_missing=tot.missing,
            chunks_shed=tot.shed_total,
            chunks_late=tot.late,
            chunks_rejected=tot.rejected_total,
            chunks_set_aside=len(seq.aside),
            ledger=led.as_dict(),
            began_at={str(StreamKey(*k)): v for k, v in seq.began.items() if v > 0},
            conflicts={str(StreamKey(*k)): n for k, n in seq.conflicts.items()},
            chunks_duplicated=sum(s.duplicated for s in streams),
            chunks_out_of_order=sum(s.out_of_order for s in streams),
            hk_received=c.hk_received,
            hk_stale_samples=c.hk_stale_samples,
            hk_missing_samples=c.hk_missing_samples,
            unknown_channel_samples=c.unknown_channel_samples,
            bad_messages=dict(books.bad_messages),
            flag_counts={name: books.flag_counts.get(name, 0) for name in fl.NAMES.values()},
            hk_age_s=self.align.hk.ages_s(now),
            rate_chunks_per_s=iv.chunks / interval_s if interval_s > 0 else 0.0,
            rate_msamples_per_s=iv.samples / interval_s / 1e6 if interval_s > 0 else 0.0,
            latency_p50_ms=float(np.percentile(lat, 50)) if lat.size else None,
            latency_p99_ms=float(np.percentile(lat, 99)) if lat.size else None,
            latency_max_ms=float(lat.max()) if lat.size else None,
            arrival_p50_ms=float(np.percentile(arr, 50)) if arr.size else None,
            arrival_p99_ms=float(np.percentile(arr, 99)) if arr.size else None,
            last_error=books.last_error,
            owns=self.owns_status() if self.owns_status is not None else self._owns,
        )

    def emit(self) -> tuple[str, bytes]:
        """The status message now; the interval figures start again."""
        msg = self.status()
        self._last_ns = self.books.now_ns
        self.books.interval.reset()
        return keys.status_key(self.books.config.setup, self.books.config.service), msg.to_bytes()

    def provenance(self) -> Provenance:
        """Parameters (TOML text), table identity, converter kind and software version."""
        from mntes_stream.io.paramfile import params_to_toml

        if self._params_toml is None:  # written once: the provenance is renewed when the noise changes
            self._params_toml = params_to_toml(self._params) if self._params else ""
        return Provenance(
            setup=self.books.config.setup,
            params_toml=self._params_toml,
            table_identity=str(self.converter.identity),
            converter_kind=str(self.converter.kind),
            software_version=__version__,
            t_ns=self._t_created_ns,
            owns=self._owns,
            noise=self._noise().provenance(sigma_p=self._sigma_p) if self._noise is not None else {},
        )

    def provenance_bytes(self) -> bytes:
        """:meth:`provenance` encoded once: identical bytes on every publication, until the noise in use
        changes (measured live, window by window)."""
        noise = self._noise() if self._noise is not None else None
        if self._provenance is None or noise is not self._provenance_noise:
            self._provenance, self._provenance_noise = self.provenance().to_bytes(), noise
        return self._provenance

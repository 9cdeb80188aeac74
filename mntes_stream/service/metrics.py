"""Prometheus metrics of any service (``[metrics]`` table; prometheus-client, the ``metrics`` extra).

:meth:`Service.start <mntes_stream.service.base.Service.start>` serves
``http://<bind>:<port>/metrics`` for the whole run when ``port`` is set; a
service needs nothing of its own. What is measured comes from three places:

- every message the service publishes (``Publishers.put`` calls
  :meth:`ServiceMetrics.observe`): messages and bytes by kind, power samples,
  and two histograms per power chunk: latency (source publication to power
  publication) and sample age (its last sample's time to power publication);
- the latest status message it published (converter): lost, duplicated,
  out-of-order chunks, bad messages by reason, flagged samples by flag name,
  housekeeping age by sensor, chunks pending;
- its heartbeat: state, uptime, queue depth, and a recorder's bytes and files.

Metric names are the contract of ``services/grafana/mntes.json`` (a test
checks every name it uses exists on a live endpoint).
"""

from __future__ import annotations

import contextlib
import logging
import threading
from dataclasses import dataclass

from mntes_stream.core.settings import Settings, setting
from mntes_stream.errors import SCHEMA_REASONS, ConfigError, SchemaError

__all__ = ["MetricsSettings", "ServiceMetrics", "MergedMetrics", "LATENCY_BUCKETS_S", "metrics_for", "require_metrics"]

log = logging.getLogger("mntes_stream.metrics")

_OWN_KEYS = frozenset({"uptime_s", "since_beat_s", "metrics_port"})
LATENCY_BUCKETS_S = (0.001, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1.0, 2.0, 5.0, 10.0)


@dataclass(frozen=True)
class MetricsSettings(Settings):
    """The ``[metrics]`` table of a service config."""

    port: int = setting(0, "serve Prometheus metrics on http://<bind>:<port>/metrics (0: off)", ge=0, le=65535)
    bind: str = setting("127.0.0.1", "address of the metrics endpoint (anything but loopback exposes it)")


def _require():
    from mntes_stream.errors import import_extra

    return import_extra("prometheus_client", "metrics")


class ServiceMetrics:
    """The metrics of one running service, in a registry of its own.

    Parameters
    ----------
    service : Service
        Its heartbeat is read at every scrape.
    """

    def __init__(self, service):
        pc = _require()
        from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily

        self._gauge, self._counter = GaugeMetricFamily, CounterMetricFamily
        self.service = service
        self.registry = pc.CollectorRegistry(auto_describe=True)
        labels = {"service": service.name, "name": service.instance_name()}
        self._labels = labels
        ln = list(labels)
        self.messages = pc.Counter("mntes_published_messages", "messages published, by key kind", [*ln, "kind"],
                                   registry=self.registry)
        self.bytes = pc.Counter("mntes_published_bytes", "payload bytes published, by key kind", [*ln, "kind"],
                                registry=self.registry)
        self.power_samples = pc.Counter("mntes_power_samples", "detector samples of optical power published", ln,
                                        registry=self.registry).labels(**labels)
        self.latency = pc.Histogram("mntes_latency_seconds", "source publication to power publication, per chunk",
                                    ln, buckets=LATENCY_BUCKETS_S, registry=self.registry).labels(**labels)
        self.sample_age = pc.Histogram("mntes_sample_age_seconds", "last sample of a power chunk to its publication "
                                       "(chunk length, network, waiting for housekeeping, conversion)", ln,
                                       buckets=LATENCY_BUCKETS_S, registry=self.registry).labels(**labels)
        self.registry.register(self)
        self._status = None
        self._lock = threading.Lock()
        self._server = None

    # ------------------------------------------------------------------ feeding

    def observe(self, key: str, payload: bytes) -> None:
        """One published message (called by ``Publishers.put``; never raises)."""
        from mntes_stream.io import keys

        kind = keys.kind_of(key) or "other"
        self.messages.labels(**self._labels, kind=kind).inc()
        self.bytes.labels(**self._labels, kind=kind).inc(len(payload))
        try:
            if kind == "power":
                self._power(payload)
            elif kind == "status":
                from mntes_stream.io.messages import StatusMessage

                status = StatusMessage.from_bytes(payload)
                with self._lock:
                    self._status = status
        except (SchemaError, ValueError, TypeError, KeyError):  # our own messages; a bug must not stop a service
            log.debug("metrics: cannot read a %s message", kind, exc_info=True)

    def _power(self, payload: bytes) -> None:
        import msgpack

        msg = msgpack.unpackb(payload, raw=False)
        shape = msg["p_opt_w"]["shape"]
        n_samples = int(shape[1])
        self.power_samples.inc(int(shape[0]) * n_samples)
        t_pub = int(msg["t_pub_ns"])
        self.latency.observe((t_pub - int(msg["source_t_pub_ns"])) / 1e9)
        if not n_samples:
            return
        if msg.get("t_ns") is not None:  # explicit times: the last int64 of the array
            last = int.from_bytes(msg["t_ns"]["data"][-8:], "little", signed=True)
        else:
            last = int(msg["t0_ns"]) + round((n_samples - 1) * 1e9 / float(msg["sample_rate_hz"]))
        self.sample_age.observe((t_pub - last) / 1e9)

    # ------------------------------------------------------------------ collecting (at scrape)

    def describe(self):
        return []  # names are dynamic; nothing to check at registration

    def collect(self):
        g, c, lab = self._gauge, self._counter, self._labels
        ln, lv = list(lab), list(lab.values())
        snap = self.service.status()
        up = g("mntes_service_up", "1 while the service is running", labels=ln)
        up.add_metric(lv, 1.0 if snap["state"] == "running" else 0.0)
        yield up
        uptime = g("mntes_service_uptime_seconds", "time since the service started", labels=ln)
        uptime.add_metric(lv, float(snap["uptime_s"]))
        yield uptime
        since = g("mntes_service_heartbeat_age_seconds", "time since the service last reported progress", labels=ln)
        since.add_metric(lv, float(snap["since_beat_s"]))
        yield since
        # Whatever else the heartbeat counts (a monitor's drops, the bridge's logged messages, a router's links).
        counters = g("mntes_service_counter", "the service's own heartbeat counters (what `ps` shows)",
                     labels=[*ln, "counter"])
        for key, value in snap.items():
            if key not in _OWN_KEYS and isinstance(value, (int, float)) and not isinstance(value, bool):
                counters.add_metric([*lv, key], float(value))
        yield counters
        depth = g("mntes_queue_depth", "messages waiting in the service's input queue", labels=[*ln, "queue"])
        if "queue_depth" in snap:
            depth.add_metric([*lv, "input"], float(snap["queue_depth"]))
        with self._lock:
            status = self._status
        if status is not None:
            depth.add_metric([*lv, "pending_chunks"], float(status.chunks_pending))
        yield depth
        if "payload_bytes" in snap and "files" in snap:  # a recorder
            for name, doc, value in (
                ("mntes_recorder_messages", "messages recorded", snap.get("messages", 0)),
                ("mntes_recorder_bytes", "payload bytes recorded", snap["payload_bytes"]),
                ("mntes_recorder_file_rotations", "new files started after the first", max(int(snap["files"]) - 1, 0)),
                ("mntes_recorder_invalid_messages", "payloads recorded that were not a valid envelope",
                 snap.get("invalid", 0)),
            ):
                m = c(name, doc, labels=ln)
                m.add_metric(lv, float(value))
                yield m
        if status is None:
            return
        chunks = c("mntes_chunks", "counts chunks by outcome (cumulative, from the status)", labels=[*ln, "outcome"])
        for outcome, value in (("received", status.chunks_received), ("converted", status.chunks_converted),
                               ("lost", status.chunks_lost), ("duplicated", status.chunks_duplicated),
                               ("out_of_order", status.chunks_out_of_order), ("missing", status.chunks_missing),
                               ("shed", status.chunks_shed), ("late", status.chunks_late),
                               ("rejected", status.chunks_rejected)):
            chunks.add_metric([*lv, outcome], float(value))
        yield chunks
        aside = g("mntes_chunks_set_aside", "chunks held under overload for late conversion now", labels=ln)
        aside.add_metric(lv, float(status.chunks_set_aside))
        yield aside
        # The ledger per stream (core/ledger.py): every chunk in one column; shed and rejected by reason.
        ledger = c("mntes_ledger_chunks", "counts chunks of each stream by ledger column (and reason)",
                   labels=[*ln, "stream", "column", "reason"])
        for stream, cols in status.ledger.items():
            for column, value in cols.items():
                for reason, n in (value.items() if isinstance(value, dict) else (("", value),)):
                    ledger.add_metric([*lv, stream, column, reason], float(n))
        yield ledger
        bad = c("mntes_bad_messages", "messages rejected, by reason", labels=[*ln, "reason"])
        for reason, value in {**dict.fromkeys(SCHEMA_REASONS, 0), **status.bad_messages}.items():
            bad.add_metric([*lv, reason], float(value))
        yield bad
        flagged = c("mntes_flagged_samples", "converted samples carrying each flag (schemas/flags.v1.json)",
                    labels=[*ln, "flag"])
        for flag, value in status.flag_counts.items():
            flagged.add_metric([*lv, flag], float(value))
        yield flagged
        samples = c("mntes_samples_converted", "samples converted (cumulative, from the status)", labels=ln)
        samples.add_metric(lv, float(status.samples_converted))
        yield samples
        age = g("mntes_hk_age_seconds", "age of the latest housekeeping reading, by sensor", labels=[*ln, "sensor"])
        for sensor, value in status.hk_age_s.items():
            age.add_metric([*lv, sensor], float(value))
        yield age

    # ------------------------------------------------------------------ serving

    def serve(self, settings: MetricsSettings) -> int:
        """Start the endpoint; returns the port. ConfigError if it cannot listen."""
        pc = _require()
        try:
            self._server, _ = pc.start_http_server(settings.port, addr=settings.bind, registry=self.registry)
        except OSError as exc:
            raise ConfigError(f"metrics: cannot serve on {settings.bind}:{settings.port}: {exc}") from None
        return self._server.server_port

    def close(self) -> None:
        if self._server is not None:
            self._server.shutdown()
            self._server.server_close()
            self._server = None


class MergedMetrics:
    """One endpoint for several services (``up --metrics-port``): every scrape reads each service's own
    endpoint (loopback) and serves their families merged by name; ``mntes_target_up`` says which answered.

    Parameters
    ----------
    urls : dict[str, str]
        ``{label: "http://127.0.0.1:<port>/metrics"}`` of each service.
    timeout_s : float
        Per service and scrape.
    """

    def __init__(self, urls: dict[str, str], timeout_s: float = 2.0):
        pc = _require()
        self.urls, self.timeout_s = dict(urls), float(timeout_s)
        self.registry = pc.CollectorRegistry(auto_describe=False)
        self.registry.register(self)
        self._server = None

    def describe(self):
        return []

    def collect(self):
        import urllib.request

        from prometheus_client.core import GaugeMetricFamily
        from prometheus_client.parser import text_string_to_metric_families

        families: dict[str, object] = {}
        up = GaugeMetricFamily("mntes_target_up", "1 if the service's own endpoint answered this scrape",
                               labels=["target"])
        for label, url in self.urls.items():
            try:
                with urllib.request.urlopen(url, timeout=self.timeout_s) as r:
                    text = r.read().decode()
            except OSError:  # stopped or not yet serving: say so, serve the others
                up.add_metric([label], 0.0)
                continue
            up.add_metric([label], 1.0)
            for fam in text_string_to_metric_families(text):
                have = families.get(fam.name)
                if have is None:
                    families[fam.name] = fam
                else:  # the same metric from another service: its samples differ by the service label
                    have.samples.extend(fam.samples)
        yield from families.values()
        yield up

    def serve(self, settings: MetricsSettings) -> int:
        """Start the endpoint; returns the port (``settings.port`` 0: any free one)."""
        pc = _require()
        try:
            self._server, _ = pc.start_http_server(settings.port, addr=settings.bind, registry=self.registry)
        except OSError as exc:
            raise ConfigError(f"metrics: cannot serve on {settings.bind}:{settings.port}: {exc}") from None
        return self._server.server_port

    close = ServiceMetrics.close


def require_metrics() -> None:
    """A one-line MissingExtraError naming the ``metrics`` extra if prometheus-client is absent."""
    _require()


@contextlib.contextmanager
def metrics_for(service):
    """Serve ``service``'s metrics while the block runs, if its config has a ``[metrics]`` port; else nothing.

    Yields the :class:`ServiceMetrics` (or None): the ``Service`` lifecycle hands its ``observe`` to
    its ``Publishers``, explicitly.
    """
    settings = getattr(service.config, "metrics", None)
    if not isinstance(settings, MetricsSettings) or not settings.port:
        yield None
        return
    metrics = ServiceMetrics(service)
    port = metrics.serve(settings)
    service.heartbeat.beat(metrics_port=port)
    log.info("%s: metrics on http://%s:%d/metrics", service.instance_name(), settings.bind, port)
    try:
        yield metrics
    finally:
        metrics.close()

"""Prometheus metrics: real HTTP GETs on live endpoints, and the Grafana dashboard's names checked against them.

``mntes-stream up --metrics-port`` runs as a subprocess (simulator, converter,
recorder in processes of their own); the test scrapes its one endpoint twice
over HTTP, parses the exposition with the reference parser, checks every
metric ``services/grafana/mntes.json`` uses exists there, and that the
throughput counters grew between the scrapes (non-zero rates).
"""

from __future__ import annotations

import json
import re
import subprocess
import sys
import threading
import time
import urllib.request
from pathlib import Path

import pytest

from mntes_stream.io.transport import free_tcp_port

parser = pytest.importorskip("prometheus_client.parser")

ROOT = Path(__file__).resolve().parents[1]
DASHBOARD = ROOT / "services" / "grafana" / "mntes.json"


def _scrape(url: str) -> dict[tuple[str, tuple], float]:
    """``{(sample name, sorted labels): value}`` of one real HTTP GET."""
    with urllib.request.urlopen(url, timeout=10) as r:
        assert r.status == 200
        text = r.read().decode()
    return {(s.name, tuple(sorted(s.labels.items()))): s.value
            for fam in parser.text_string_to_metric_families(text) for s in fam.samples}


def _dashboard_metrics() -> set[str]:
    """Every ``mntes_*`` name in the dashboard's queries."""
    doc = json.loads(DASHBOARD.read_text())
    exprs = [t["expr"] for p in doc["panels"] for t in p["targets"]]
    assert exprs
    return {m for e in exprs for m in re.findall(r"\b(mntes_[a-z_]+)\b", e)}


def _total(samples: dict, name: str, **labels) -> float:
    return sum(v for (n, lab), v in samples.items() if n == name and set(labels.items()) <= set(lab))


def test_up_serves_every_dashboard_metric_with_nonzero_rates(tmp_path):
    port = free_tcp_port()
    proc = subprocess.Popen([sys.executable, "-m", "mntes_stream", "up", "--duration", "60", "--out", str(tmp_path),
                             "--modules", "2", "--channels", "16", "--metrics-port", str(port)],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    lines: list[str] = []
    threading.Thread(target=lambda: lines.extend(proc.stdout), daemon=True).start()
    url = f"http://127.0.0.1:{port}/metrics"
    try:
        deadline = time.monotonic() + 120
        while True:  # until power flows (a loaded machine can take seconds to build tables)
            assert proc.poll() is None and time.monotonic() < deadline, "".join(lines)
            try:
                first = _scrape(url)
                if _total(first, "mntes_power_samples_total") > 0 and _total(first, "mntes_recorder_bytes_total") > 0:
                    break
            except OSError:  # not serving yet
                pass
            time.sleep(0.5)
        time.sleep(3.0)
        second = _scrape(url)
    finally:
        proc.terminate()  # SIGTERM: up stops its services in order
        proc.wait(60)
    names = {n for n, _ in second}
    used = _dashboard_metrics()
    assert len(used) >= 15
    missing = used - names
    assert not missing, f"dashboard uses metrics the endpoint does not serve: {sorted(missing)}"
    # Each service is scraped through the one endpoint.
    assert {dict(lab)["target"] for n, lab in second if n == "mntes_target_up"} == {"recorder", "converter", "source"}
    assert all(v == 1.0 for (n, _), v in second.items() if n in ("mntes_target_up", "mntes_service_up"))
    # Rates: what flows grew between the two scrapes.
    for name, labels in [("mntes_power_samples_total", {}), ("mntes_published_messages_total", {"kind": "counts"}),
                         ("mntes_published_messages_total", {"kind": "power"}), ("mntes_published_bytes_total", {}),
                         ("mntes_latency_seconds_count", {}), ("mntes_latency_seconds_sum", {}),
                         ("mntes_sample_age_seconds_count", {}),
                         ("mntes_chunks_total", {"outcome": "converted"}), ("mntes_samples_converted_total", {}),
                         ("mntes_flagged_samples_total", {"flag": "saturated"}), ("mntes_recorder_bytes_total", {}),
                         ("mntes_recorder_messages_total", {})]:
        assert _total(second, name, **labels) > _total(first, name, **labels), (name, labels)  # a non-zero rate
    # Latency buckets are cumulative; the samples-per-second rate is the array's own rate.
    rate = (_total(second, "mntes_power_samples_total") - _total(first, "mntes_power_samples_total")) / 3.0
    assert 0.3 * 32 * 152.6 < rate < 3 * 32 * 152.6
    assert _total(second, "mntes_flagged_samples_total", flag="saturated") <= _total(second, "mntes_samples_converted_total")
    assert {dict(lab)["sensor"] for n, lab in second if n == "mntes_hk_age_seconds"} >= {"t_bath", "b_field"}
    assert _total(second, "mntes_chunks_total", outcome="lost") == 0
    # The ledger per stream adds up to the status's totals (one status message behind both).
    assert {dict(lab)["stream"] for n, lab in second if n == "mntes_ledger_chunks_total"} == {"0/0", "0/1"}
    assert (_total(second, "mntes_ledger_chunks_total", column="received")
            == _total(second, "mntes_chunks_total", outcome="received") > 0)


def _required(name: str) -> dict:
    return {"params": "params.toml"} if name == "converter" else {}


def test_every_service_takes_a_metrics_table():
    from mntes_stream.service.metrics import MetricsSettings
    from mntes_stream.service.registry import SERVICES

    without = {name for name, cls in SERVICES.items()
               if not isinstance(getattr(cls.Config(**_required(name)), "metrics", None), MetricsSettings)}
    assert not without, without
    assert MetricsSettings().bind == "127.0.0.1" and MetricsSettings().port == 0


def test_a_service_alone_serves_its_heartbeat(tmp_path):
    """``serve --config`` with a [metrics] table: a router's own endpoint, loopback."""
    zport, mport = free_tcp_port(), free_tcp_port()
    cfg = tmp_path / "router.toml"
    cfg.write_text(f'[router]\nsetup = "lab"\n[metrics]\nport = {mport}\n[zenoh]\nlisten = ["tcp/127.0.0.1:{zport}"]\n')
    proc = subprocess.Popen([sys.executable, "-m", "mntes_stream", "serve", "--config", str(cfg), "--duration", "30"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 60
        while True:
            try:
                got = _scrape(f"http://127.0.0.1:{mport}/metrics")
                if _total(got, "mntes_service_up") == 1.0 and any(dict(lab).get("counter") == "links" for _, lab in got):
                    break  # running, and its first heartbeat (links to clients and routers) is in
            except OSError:
                pass
            assert proc.poll() is None and time.monotonic() < deadline, proc.communicate()
            time.sleep(0.2)
        assert ("mntes_service_counter", (("counter", "zenoh_ids_seen"), ("name", "router"), ("service", "router"))) in got
        # Bound to loopback only: the socket the process holds says so.
        psutil = pytest.importorskip("psutil")
        held = [c.laddr for c in psutil.Process(proc.pid).net_connections("tcp") if c.laddr.port == mport]
        assert held and all(a.ip == "127.0.0.1" for a in held)
    finally:
        proc.terminate()
        proc.wait(30)


def test_the_monitor_serves_its_heartbeat(tmp_path):
    """The monitor too: ``serve --config`` of a [monitor] with [metrics] answers on loopback."""
    mport = free_tcp_port()
    cfg = tmp_path / "monitor.toml"
    cfg.write_text(f'[monitor]\nsetup = "lab"\nport = 0\n[metrics]\nport = {mport}\n')
    proc = subprocess.Popen([sys.executable, "-m", "mntes_stream", "serve", "--config", str(cfg), "--duration", "30"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 60
        while True:
            try:
                got = _scrape(f"http://127.0.0.1:{mport}/metrics")
                if _total(got, "mntes_service_up") == 1.0:
                    break
            except OSError:
                pass
            assert proc.poll() is None and time.monotonic() < deadline, proc.communicate()
            time.sleep(0.2)
        assert {dict(lab).get("service") for n, lab in got if n == "mntes_service_up"} == {"monitor"}
    finally:
        proc.terminate()
        proc.wait(30)


@pytest.mark.parametrize("argv", [["up", "--duration", "1", "--metrics-port", "0"],
                                  ["serve", "--config", "services/router.toml", "--set", "metrics.port=1",
                                   "--duration", "1"]])
def test_missing_prometheus_client_is_one_line_naming_the_extra(argv, tmp_path):
    code = ("import sys; sys.modules['prometheus_client'] = None\n"
            "from mntes_stream.cli import main\n"
            f"sys.exit(main({argv!r} + (['--out', {str(tmp_path)!r}] if {argv[0]!r} == 'up' else [])))")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert res.returncode == 2, res.stderr
    err = res.stderr.strip().splitlines()
    assert len(err) == 1 and "pip install 'mntes-stream[metrics]'" in err[0], res.stderr


def test_observed_power_chunk_gives_samples_latency_and_sample_age():
    """One power chunk with known times through ``ServiceMetrics.observe``; the histograms' sums are exact."""
    import numpy as np
    from prometheus_client import generate_latest

    from mntes_stream.io.messages import PowerChunk, detector_ids_for
    from mntes_stream.service.metrics import ServiceMetrics
    from mntes_stream.service.router import RouterConfig, RouterService

    metrics = ServiceMetrics(RouterService(RouterConfig()))  # never run: only its heartbeat is read
    ch = np.arange(3, dtype=np.int32)
    t0, src_pub, pub = 1_700_000_000_000_000_000, 1_700_000_000_150_000_000, 1_700_000_000_162_000_000
    p = np.full((3, 20), 1e-12)
    f = np.zeros((3, 20), np.uint16)
    for kw in ({"t0_ns": t0, "sample_rate_hz": 200.0}, {"t0_ns": None, "sample_rate_hz": None,
                                                         "t_ns": t0 + 5_000_000 * np.arange(20, dtype=np.int64)}):
        chunk = PowerChunk("lab", 0, 1, ch, detector_ids_for(0, 1, ch), 7, kw.pop("t0_ns"), kw.pop("sample_rate_hz"),
                           p, f, "tables", "table", src_pub, pub, **kw)
        metrics.observe("mntes/lab/power/0/1", chunk.to_bytes())
    got = {(s.name, s.labels.get("le")): s.value
           for fam in parser.text_string_to_metric_families(generate_latest(metrics.registry).decode())
           for s in fam.samples}
    assert got[("mntes_power_samples_total", None)] == 2 * 60
    assert got[("mntes_latency_seconds_sum", None)] == pytest.approx(2 * 0.012, abs=1e-12)
    # last sample at t0 + 19 x 5 ms = t0 + 95 ms; published at t0 + 162 ms: 67 ms old, both ways of giving times
    assert got[("mntes_sample_age_seconds_sum", None)] == pytest.approx(2 * 0.067, abs=1e-12)
    assert got[("mntes_sample_age_seconds_bucket", "0.05")] == 0 and got[("mntes_sample_age_seconds_bucket", "0.1")] == 2
    assert got[("mntes_published_messages_total", None)] == 2

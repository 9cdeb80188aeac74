"""Source -> converter -> zenoh -> recorder (rotated MCAP) -> export -> HDF5: the converter's power, bitwise.

Also runs ``examples/bin_map.py --demo``: simulate a scan, record, export, bin a map.
"""

from __future__ import annotations

import json
import subprocess
import sys
import threading
import time
import warnings
from pathlib import Path

import h5py
import numpy as np
from test_feeds import bits

from mntes_stream.core import flags as fl
from mntes_stream.core.convert import make_converter
from mntes_stream.feeds import RecordedPower, export_hdf5, read_hdf5
from mntes_stream.io import keys
from mntes_stream.io import mcap as mio
from mntes_stream.io.messages import PowerChunk
from mntes_stream.io.transport import Publishers, free_tcp_port, loopback, open_session
from mntes_stream.pipeline import ConverterPipeline, PipelineConfig
from mntes_stream.service.recorder import RecorderConfig, ZenohSettings, run_recorder
from mntes_stream.service.source import MinimalSource, SourceConfig

T0 = 1_700_000_000_000_000_000
ROOT = Path(__file__).resolve().parents[1]


def _converted(steps: int):
    """The converter's outputs for ``steps`` chunks per module: (provenance bytes, [(key, power bytes)], pipeline)."""
    src = MinimalSource(SourceConfig(setup="lab", modules=2, channels=4, sample_rate_hz=200.0, chunk_s=0.1))
    # One detector without parameters: the converter flags it UNKNOWN_CHANNEL with NaN power.
    conv = make_converter("exact", {p.detector_id: p for p in src.params[1:]})
    pipe = ConverterPipeline(conv, PipelineConfig(setup="lab"), clock=None)
    out = []
    for t_pub, batch in src.batches(T0, duration_s=steps * 0.1):
        for key, payload in batch:
            out += pipe.handle(key, payload, t_pub)
    out += pipe.flush()
    return pipe.provenance_bytes(), [(k, p) for k, p in out if "/power/" in k], pipe


def _recorded_count(directory) -> int:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", mio.TruncatedFileWarning)
        try:
            return mio.Session(directory, warn=False).count()
        except Exception:  # nothing flushed yet
            return 0


def test_recorded_converter_power_exports_bitwise_with_gaps_flagged(tmp_path):
    prov, power, pipe = _converted(30)
    assert len(power) == 60
    assert all(np.all(c.flags[0] & fl.UNKNOWN_CHANNEL) and np.isnan(c.p_opt_w[0]).all() for c in
               (PowerChunk.from_bytes(p) for k, p in power if k.endswith("/0/0")))
    chunks = [PowerChunk.from_bytes(p) for _, p in power]
    lost = {(0, 7), (0, 8), (1, 20)}  # (module, seq) never published: a lossy link
    plan = [(keys.provenance_key("lab"), prov)] + [
        (k, p) for (k, p), c in zip(power, chunks) if (c.module, c.seq) not in lost
    ]
    plan.append(next((k, p) for (k, p), c in zip(power, chunks) if (c.module, c.seq) == (1, 3)))  # a repeat

    port = free_tcp_port()
    cfg = RecorderConfig(setup="lab", directory=str(tmp_path / "rec"), prefix="s", flush_interval_s=0.1,
                         rotate_mb=0.01, zenoh=ZenohSettings(listen=(f"tcp/127.0.0.1:{port}",)))
    stop, result = threading.Event(), {}
    th = threading.Thread(target=lambda: result.update(stats=run_recorder(cfg, stop)))
    th.start()
    try:
        with open_session(loopback(connect_ports=[port])) as z:
            pubs = Publishers(z)
            assert pubs.wait_matching({k for k, _ in plan}, 30.0)
            for key, payload in plan:
                pubs.put(key, payload)
            deadline = time.monotonic() + 30
            while _recorded_count(tmp_path / "rec") < len(plan) and time.monotonic() < deadline:
                time.sleep(0.05)
            pubs.close()
    finally:
        stop.set()
        th.join(30)
    files = result["stats"].files
    assert len(files) >= 3  # rotated: the session is several files

    summary = export_hdf5(tmp_path / "rec", tmp_path / "x.h5")
    assert summary.duplicate_chunks == 1 and summary.gap_samples == 3 * 20
    back = read_hdf5(tmp_path / "x.h5")
    assert sorted(back) == ["lab_b0m0", "lab_b0m1"]
    assert all(b.table_identities == (pipe.converter.identity,) for b in back.values())  # the power's identity
    for m in (0, 1):
        b = back[f"lab_b0m{m}"]
        assert b.n_samples == 30 * 20 and np.all(np.diff(b.t_ns) > 0)
        for c in (c for c in chunks if c.module == m):
            cols = slice(c.seq * 20, (c.seq + 1) * 20)
            np.testing.assert_array_equal(b.t_ns[cols], c.times_ns())
            rows = [b.detectors.index(d) for d in c.detector_ids]
            if (m, c.seq) in lost:
                assert np.all(b.flags[:, cols] == fl.GAP) and np.all(np.isnan(b.p_opt_w[:, cols]))
            else:
                np.testing.assert_array_equal(bits(b.p_opt_w[rows, cols]), bits(c.p_opt_w))
                np.testing.assert_array_equal(b.flags[rows, cols], c.flags)
    with h5py.File(tmp_path / "x.h5") as f:
        p = f["provenance/0"].attrs
        assert p["params_toml"] == pipe.provenance().params_toml and p["params_toml"]
        assert p["table_identity"] == pipe.converter.identity
        assert json.loads(f["lab_b0m0"].attrs["table_identities"]) == [pipe.converter.identity]
        assert json.loads(f["lab_b0m0"].attrs["converter_kinds"]) == ["exact"]
        assert len(json.loads(f.attrs["source_files"])) == len(files)
        assert json.loads(f.attrs["recording"])[0]["software"].startswith("mntes-stream")
    # The same session, read directly, agrees with the export.
    direct = RecordedPower(files).read()
    np.testing.assert_array_equal(bits(direct["lab_b0m1"].p_opt_w), bits(back["lab_b0m1"].p_opt_w))


def test_bin_map_example_round_trip(tmp_path):
    out = subprocess.run([sys.executable, str(ROOT / "examples" / "bin_map.py"), "--demo", str(tmp_path), "--json",
                          "--png", str(tmp_path / "map.png")], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    r = json.loads(out.stdout)
    assert r["dropped_chunks"] > 0 and r["gap_samples"] == r["dropped_chunks"] * 25 and r["gap_samples_all_nan"]
    assert r["hit_pixels"] == r["pixels"]
    assert r["max_rel_error"] < 1e-12  # binning the export gives back the sky
    assert (tmp_path / "map.png").stat().st_size > 1000
    # The example's loader sees the layout the README documents.
    with h5py.File(r["file"]) as f:
        g = f[r["observation"]]
        assert {"tod", "time", "time_ns", "flags", "detectors", "channels"} <= set(g)
        assert g["tod"].shape == (r["detectors"], r["samples"])

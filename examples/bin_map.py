#!/usr/bin/env python3
"""Bin exported power into a 2-D map with numpy only: the mapmaking round trip.

    python examples/bin_map.py EXPORT.h5 [--obs NAME] [--png map.png]
    python examples/bin_map.py --demo DIR [--png map.png] [--json]

An exported file (``mntes-stream export``) holds, per observation (module),
``tod`` (detectors x samples, W), ``time_ns``, ``flags`` and ``channels``.
Power carries no pointing, so this example reconstructs it from time with a
known raster scan (:func:`pointing_deg`: triangle sweeps in x, slow steps in
y, detectors offset along x by channel). A binned map is then the mean of the
usable samples falling in each pixel (flagged or NaN samples are skipped: gaps
are NaN + GAP in the export, never zeros).

``--demo`` makes the whole round trip: it simulates the scan over a known sky
(piecewise constant on the map's pixels, so binning recovers it exactly),
writes the power chunks to an MCAP session (dropping a few chunks, as a lossy
link would), exports it with ``mntes_stream.feeds.export_hdf5`` and bins the
file, printing the largest difference between map and sky.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

# --- the scan and the map (what a mapmaker would get from the telescope's pointing) --------

SCAN_T0_NS = 1_700_000_000_000_000_000  # scan start (ns since the epoch)
X_HALF_DEG, Y_HALF_DEG = 4.0, 2.0        # map half-widths
PIX_DEG = 0.25                           # square pixels
X_PERIOD_S, Y_PERIOD_S = 3.0, 120.0      # triangle sweep periods
DET_SPACING_DEG = 0.1                    # detector offsets along x, by channel
UNUSABLE = 0x01 | 0x02 | 0x04 | 0x20 | 0x40 | 0x80 | 0x100  # core.flags.UNUSABLE (kept literal: numpy only)


def _triangle(t_s: np.ndarray, period_s: float) -> np.ndarray:
    """-1 .. 1 .. -1 over one period."""
    phase = np.mod(t_s / period_s, 1.0)
    return 4.0 * np.abs(phase - 0.5) - 1.0


def pointing_deg(time_ns: np.ndarray, channels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Where each detector looks: x, y in degrees, each of shape (n_det, n_samp)."""
    t_s = (np.asarray(time_ns, dtype=np.int64) - SCAN_T0_NS) / 1e9
    x0 = 0.9 * X_HALF_DEG * _triangle(t_s, X_PERIOD_S)
    y0 = 0.95 * Y_HALF_DEG * _triangle(t_s, Y_PERIOD_S)
    offset = (np.asarray(channels, dtype=float) - np.mean(channels)) * DET_SPACING_DEG
    return x0[None, :] + offset[:, None], np.broadcast_to(y0, (len(channels), t_s.size))


def pixel_index(x_deg: np.ndarray, y_deg: np.ndarray) -> tuple[np.ndarray, tuple[int, int]]:
    """Flat pixel index of each sample (-1 off the map) and the map shape (ny, nx)."""
    nx, ny = int(round(2 * X_HALF_DEG / PIX_DEG)), int(round(2 * Y_HALF_DEG / PIX_DEG))
    ix = np.floor((x_deg + X_HALF_DEG) / PIX_DEG).astype(np.int64)
    iy = np.floor((y_deg + Y_HALF_DEG) / PIX_DEG).astype(np.int64)
    ok = (ix >= 0) & (ix < nx) & (iy >= 0) & (iy < ny)
    return np.where(ok, iy * nx + ix, -1), (ny, nx)


def bin_map(tod_w: np.ndarray, flags: np.ndarray, pix: np.ndarray, shape: tuple[int, int]):
    """Binned map (mean of usable samples per pixel, NaN where unhit) and hit counts, shape (ny, nx)."""
    good = ((flags & UNUSABLE) == 0) & np.isfinite(tod_w) & (pix >= 0)
    n_pix = shape[0] * shape[1]
    hits = np.bincount(pix[good], minlength=n_pix)
    total = np.bincount(pix[good], weights=tod_w[good], minlength=n_pix)
    with np.errstate(invalid="ignore", divide="ignore"):
        m = np.where(hits > 0, total / np.maximum(hits, 1), np.nan)
    return m.reshape(shape), hits.reshape(shape)


def sky_w(shape: tuple[int, int]) -> np.ndarray:
    """The demo sky, W per pixel (ny, nx): a loading level, a gradient and two sources."""
    ny, nx = shape
    y, x = np.mgrid[0:ny, 0:nx]
    s = 1.0e-12 + 2.0e-15 * (x - nx / 2)
    s += 5.0e-14 * np.exp(-((x - 0.3 * nx) ** 2 + (y - 0.5 * ny) ** 2) / 4.0)
    s += 3.0e-14 * np.exp(-((x - 0.7 * nx) ** 2 + (y - 0.3 * ny) ** 2) / 2.0)
    return s


# --- loading an export (h5py) ----------------------------------------------------------------


class BinMapError(Exception):
    """Bad input: said in one line, exit code 2."""


def load_observation(path, obs: str | None = None) -> dict:
    """One observation of an exported file as numpy arrays (plus its attributes)."""
    import h5py

    if not Path(path).is_file():
        raise BinMapError(f"{path}: no such file (an `mntes-stream export` HDF5 file)")
    with h5py.File(path, "r") as f:
        if "observations" not in f.attrs:
            raise BinMapError(f"{path}: not an `mntes-stream export` HDF5 file (no observations attribute)")
        names = json.loads(f.attrs["observations"])
        if not names or (obs is not None and obs not in names):
            raise BinMapError(f"{path}: no observation {obs!r}; it has {', '.join(names) or 'none'}")
        name = obs or names[0]
        g = f[name]
        return {
            "name": name,
            "tod": g["tod"][()],
            "time_ns": g["time_ns"][()],
            "flags": g["flags"][()],
            "channels": g["channels"][()],
            "detectors": [d.decode() if isinstance(d, bytes) else str(d) for d in g["detectors"][()]],
            "units": g["tod"].attrs["units"],
            "attrs": {k: (v.item() if hasattr(v, "item") else v) for k, v in g.attrs.items()},
        }


def map_of_file(path, obs: str | None = None):
    o = load_observation(path, obs)
    x, y = pointing_deg(o["time_ns"], o["channels"])
    pix, shape = pixel_index(x, y)
    m, hits = bin_map(o["tod"], o["flags"], pix, shape)
    return o, m, hits


# --- the demo: simulate, record, export, bin -------------------------------------------------


def write_demo_session(directory: Path, n_det: int = 16, rate_hz: float = 50.0, seconds: float = 120.0,
                       chunk_s: float = 0.5, drop_every: int = 17, noise_w: float = 0.0, seed: int = 1) -> dict:
    """An MCAP session of the scan over :func:`sky_w`; every ``drop_every``-th chunk is lost."""
    from mntes_stream.core.align import sample_times_ns
    from mntes_stream.core.ids import detector_id
    from mntes_stream.io import keys
    from mntes_stream.io.mcap import McapFileWriter
    from mntes_stream.io.messages import PowerChunk, Provenance

    rng = np.random.default_rng(seed)
    channels = np.arange(n_det, dtype=np.int32)
    ids = [detector_id(0, 0, c) for c in channels]
    n = int(round(rate_hz * chunk_s))
    n_chunks = int(round(seconds / chunk_s))
    step_ns = int(round(chunk_s * 1e9))
    directory.mkdir(parents=True, exist_ok=True)
    dropped = 0
    with McapFileWriter(directory / "demo-000001.mcap") as w:
        prov = Provenance(setup="demo", params_toml="# demo: power simulated directly, no detector model\n",
                          table_identity="demo-sky", converter_kind="simulated", software_version="examples/bin_map.py",
                          t_ns=SCAN_T0_NS)
        w.write(keys.provenance_key("demo"), prov.to_bytes(), SCAN_T0_NS)
        for k in range(n_chunks):
            t0 = SCAN_T0_NS + k * step_ns
            if drop_every and k % drop_every == drop_every - 1:
                dropped += 1
                continue
            t = sample_times_ns(t0, rate_hz, n)
            x, y = pointing_deg(t, channels)
            pix, shape = pixel_index(x, y)
            p = np.where(pix >= 0, sky_w(shape).ravel()[np.maximum(pix, 0)], np.nan)
            if noise_w:
                p = p + rng.normal(0.0, noise_w, p.shape)
            flags = np.where(pix >= 0, 0, 0x04).astype(np.uint16)  # off the sky: flagged out of range
            chunk = PowerChunk(setup="demo", board=0, module=0, channels=channels, detector_ids=ids, seq=k, t0_ns=t0,
                               sample_rate_hz=rate_hz, p_opt_w=p, flags=flags, table_identity="demo-sky",
                               converter_kind="simulated", source_t_pub_ns=t0, t_pub_ns=t0 + step_ns)
            w.write(keys.power_key("demo", 0, 0), chunk.to_bytes(), t0 + step_ns)
    return {"chunks": n_chunks, "dropped_chunks": dropped, "samples_per_chunk": n}


def demo(directory: Path, png: str | None = None) -> dict:
    from mntes_stream.feeds import export_hdf5

    directory = Path(directory)
    sim = write_demo_session(directory / "session")
    summary = export_hdf5(directory / "session", directory / "demo.h5", overwrite=True)
    o, m, hits = map_of_file(directory / "demo.h5")
    truth = sky_w(m.shape)
    hit = hits > 0
    err = np.abs(m[hit] - truth[hit])
    gap = (o["flags"] & 0x100) != 0
    result = {
        "file": str(directory / "demo.h5"),
        "observation": o["name"],
        "detectors": len(o["detectors"]),
        "samples": int(o["time_ns"].size),
        "dropped_chunks": sim["dropped_chunks"],
        "gap_samples": int(gap[0].sum()),
        "gap_samples_all_nan": bool(np.isnan(o["tod"][gap]).all()),
        "hit_pixels": int(hit.sum()),
        "pixels": int(hit.size),
        "max_abs_error_w": float(err.max()),
        "max_rel_error": float((err / truth[hit]).max()),
        "export_samples_per_s": round(summary.samples_per_s),
    }
    if png:
        save_png(m, truth, png)
        result["png"] = png
    return result


def save_png(m: np.ndarray, truth: np.ndarray | None, path: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = [("binned map (pW)", m)] + ([("input sky (pW)", truth)] if truth is not None else [])
    fig, axes = plt.subplots(1, len(panels), figsize=(5 * len(panels), 3), squeeze=False)
    ext = (-X_HALF_DEG, X_HALF_DEG, -Y_HALF_DEG, Y_HALF_DEG)
    for ax, (title, img) in zip(axes[0], panels):
        im = ax.imshow(img * 1e12, origin="lower", extent=ext)
        ax.set_title(title)
        ax.set_xlabel("x (deg)")
        ax.set_ylabel("y (deg)")
        fig.colorbar(im, ax=ax)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("file", nargs="?", help="an exported HDF5 file")
    ap.add_argument("--obs", help="observation (group) name; default the first")
    ap.add_argument("--demo", metavar="DIR", help="simulate, record, export and bin into DIR")
    ap.add_argument("--png", help="save the map as a PNG")
    ap.add_argument("--json", action="store_true", help="print the result as one JSON document")
    args = ap.parse_args(argv)
    try:
        return _run(ap, args)
    except (BinMapError, OSError) as exc:
        print(f"bin_map.py: error: {exc}", file=sys.stderr)
        return 2


def _run(ap, args) -> int:
    if args.demo:
        result = demo(Path(args.demo), args.png)
    elif args.file:
        o, m, hits = map_of_file(args.file, args.obs)
        if args.png:
            save_png(m, None, args.png)
        result = {"observation": o["name"], "hit_pixels": int((hits > 0).sum()), "pixels": int(hits.size),
                  "map_mean_w": float(np.nanmean(m)), "units": o["units"]}
    else:
        ap.error("give an exported file or --demo DIR")
    print(json.dumps(result, indent=2) if args.json else "\n".join(f"{k:>22s}: {v}" for k, v in result.items()))
    return 0


if __name__ == "__main__":
    sys.exit(main())

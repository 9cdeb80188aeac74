#!/usr/bin/env python3
"""A binned HEALPix map of recorded power with litebird_sim's own loader and binner.

    python examples/litebird_binned_map.py [--work DIR] [--session REC] [--duration S] [--json]

Records a few seconds with ``mntes-stream up`` (or takes ``--session``),
exports them with ``mntes-stream export --format litebird_sim`` (one
``write_list_of_observations`` file per module), loads them with
``litebird_sim.read_list_of_observations`` (``tod_dtype=float64``: its default
float32 would round the power) and bins them with
``litebird_sim.make_binned_map``.

What litebird_sim cannot know from a readout, the example states:

- the TOD is power in W; litebird_sim has no watt unit, so its loader reports
  K_CMB (with a warning): the map is in W whatever the label says;
- its binner reads no flags: detectors usable less than half the time are
  left out,
  and each observation is cut to the longest span where the others are all
  usable (``local_flags & UNUSABLE == 0``; NaN power elsewhere);
- it weights detectors by ``net_ukrts`` (a temperature NET, 0 in the export):
  equal weights here;
- the readout carries no pointing: a made-up scan (10 degree sweeps every
  2 s, drifting in longitude, polarisation angle turning at 46 rpm like a
  HWP) is given as ``pointings``.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _record import arguments, fail, longest_run, record_and_export, report, usable_detectors  # noqa: E402

NSIDE = 64


def scan(obs) -> np.ndarray:
    """Made-up pointing (theta, phi, psi) in rad for every detector and sample, shape (n_det, n_samp, 3)."""
    t_s = obs.get_times(normalize=True)
    theta = np.deg2rad(60.0 + 5.0 * np.sin(2 * np.pi * t_s / 2.0))
    phi = np.deg2rad(6.0 * t_s)
    psi = 2 * np.pi * 46.0 / 60.0 * t_s
    return np.broadcast_to(np.stack([theta, phi, psi], axis=-1), (obs.n_detectors, obs.n_samples, 3)).copy()


def main() -> None:
    args = arguments(__doc__.splitlines()[0])
    import h5py
    import litebird_sim as lbs

    from mntes_stream.core.flags import UNUSABLE

    out = record_and_export(args, "litebird_sim")
    files = sorted(out.glob("*.h5"))
    loaded = lbs.read_list_of_observations(files, tod_dtype=np.float64, limit_mpi_rank=False)
    with h5py.File(files[0], "r") as f:
        units_in_file = str(f["tod"].attrs["units"])
    usable_obs, cut = [], 0
    for obs in loaded:
        bad = (obs.local_flags & UNUSABLE) != 0  # (det, samp): no usable power (NaN)
        keep = np.flatnonzero(usable_detectors(bad))
        cut += obs.n_detectors - keep.size
        a, z = longest_run(~bad[keep].any(axis=0))  # the binner reads no flags: only all-usable samples
        if z - a < 2:
            continue
        sub = lbs.Observation(detectors=[obs.detectors_global[i] for i in keep], n_samples_global=z - a,
                              start_time_global=obs.start_time + a / obs.sampling_rate_hz,
                              sampling_rate_hz=obs.sampling_rate_hz, tods=obs.tod_list)
        sub.tod[:] = obs.tod[keep, a:z]
        sub.net_ukrts = np.ones(sub.n_detectors)
        usable_obs.append(sub)
    if not usable_obs:
        fail(f"{out}: no detector usable at least half the time: no usable power to map")
    result = lbs.make_binned_map(nside=NSIDE, observations=usable_obs, pointings=[scan(o) for o in usable_obs],
                                 output_coordinate_system=lbs.CoordinateSystem.Ecliptic)
    i_map_w = result.binned_map[0]
    seen = i_map_w != -1.6375e30  # healpy's UNSEEN: pixels the scan did not constrain
    report(args, {
        "observations": len(loaded),
        "detectors_kept": sum(o.n_detectors for o in usable_obs),
        "samples_used": int(sum(o.n_samples for o in usable_obs)),
        "detectors_cut": cut,
        "units_in_file": units_in_file,
        "units_litebird_reports": str(loaded[0].tod_list[0].units.value),
        "nside": NSIDE,
        "pixels_seen": int(seen.sum()),
        "mean_power_w": float(i_map_w[seen].mean()),
        "mean_power_w_from_tod": float(np.mean([o.tod.mean() for o in usable_obs])),
    })


if __name__ == "__main__":
    main()

#!/usr/bin/env python3
"""Power spectra of recorded power with TOAST's own loader and noise estimator.

    python examples/toast_noise_psd.py [--work DIR] [--session REC] [--duration S] [--json]

Records a few seconds with ``mntes-stream up`` (or takes ``--session``),
exports them with ``mntes-stream export --format toast`` (one
``toast.io.save_hdf5`` file per module), loads each file with
``toast.io.load_hdf5`` into a ``toast.Data`` and runs ``toast.ops.NoiseEstim``
on ``signal`` (W), skipping the samples whose TOAST flags carry
``det_mask_invalid`` (our unusable samples, NaN power). TOAST's noise *model*
(``toast.noise.Noise``) accepts only K^2 s, so the PSDs go to NoiseEstim's
FITS files (``output_dir``), read back here: W^2/Hz, one file per detector.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _record import arguments, fail, record_and_export, report  # noqa: E402


def main() -> None:
    args = arguments(__doc__.splitlines()[0])
    import toast  # before anything that may load spt3g
    import toast.ops
    from astropy.io import fits
    from toast.io import load_hdf5

    out = record_and_export(args, "toast")
    comm = toast.Comm(world=None)
    data = toast.Data(comm)
    for path in sorted(out.glob("*.h5")):
        data.obs.append(load_hdf5(str(path), comm))
    psd_dir = Path(args.work) / "toast-psd"
    flagged = toast.observation.default_values.det_mask_invalid
    toast.ops.NoiseEstim(det_data="signal", det_flags="flags", det_flag_mask=flagged, shared_flags="flags",
                         shared_flag_mask=1, lagmax=64, nbin_psd=None, out_model=None,
                         output_dir=str(psd_dir)).apply(data)
    levels, files = {}, 0
    for path in sorted(psd_dir.glob("*.fits")):  # one per detector with valid samples
        files += 1
        with fits.open(path) as h:
            freq_hz, psd_w2_per_hz = (np.asarray(r[0], dtype=np.float64) for r in h[2].data)
            det = h[2].header["DET1"]
        white = psd_w2_per_hz[freq_hz > 10.0]  # above the HWP and drift lines
        if np.isfinite(white).all():  # NoiseEstim gives NaN where too few samples were valid
            levels[det] = float(np.sqrt(np.median(white)))
    if not levels:
        fail(f"{out}: no detector with a finite spectrum: no usable power in the recording?")
    report(args, {
        "observations": [ob.name for ob in data.obs],
        "detectors": sum(len(ob.all_detectors) for ob in data.obs),
        "signal_units": str(data.obs[0].detdata["signal"].units),
        "sample_rate_hz": float(data.obs[0].telescope.focalplane.sample_rate.to_value("Hz")),
        "psd_files": files,
        "finite_spectra": len(levels),
        "white_noise_w_per_rthz_median": float(np.median(list(levels.values()))),
    })


if __name__ == "__main__":
    main()

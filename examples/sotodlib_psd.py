#!/usr/bin/env python3
"""Power spectra of recorded power with sotodlib's own loader and FFT operators.

    python examples/sotodlib_psd.py [--work DIR] [--session REC] [--duration S] [--json]

Records a few seconds with ``mntes-stream up`` (or takes ``--session``),
exports them with ``mntes-stream export --format sotodlib`` (one
``AxisManager.save`` group per module; the root attribute ``observations``
names them), loads each with ``AxisManager.load``, drops the detectors whose
``flags.unusable`` range matrix cuts half the samples or more (a latched
channel, usable now and then), restricts the samples to
the longest span the others have all usable (``AxisManager.restrict``: the
power is NaN where cut) and computes Welch spectra of ``signal`` (W) with
``sotodlib.tod_ops.fft_ops.calc_psd``: W^2/Hz.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _record import arguments, fail, longest_run, record_and_export, report, usable_detectors  # noqa: E402


def main() -> None:
    args = arguments(__doc__.splitlines()[0])
    import h5py
    from sotodlib import core
    from sotodlib.tod_ops import fft_ops

    out = record_and_export(args, "sotodlib")
    with h5py.File(out, "r") as f:
        names = json.loads(f.attrs["observations"])
    levels, kept, cut, used, rate_hz, units = [], 0, 0, 0, None, None
    for name in names:
        aman = core.AxisManager.load(str(out), name)
        cuts = aman.flags.unusable.mask()  # (dets, samps): samples with no usable power (NaN)
        alive = usable_detectors(cuts)
        cut += int((~alive).sum())
        rate_hz, units = float(aman.mntes_stream.sample_rate_hz), str(aman.mntes_stream.signal_units)
        if not alive.any():
            continue  # no detector of this module with power most of the time
        aman.restrict("dets", aman.dets.vals[alive])
        # Welch needs gap-free data: the longest span where every kept detector is usable.
        a, z = longest_run(~cuts[alive].any(axis=0))
        if z - a < 128:
            fail(f"{name}: no span of 128 samples where all {aman.dets.count} detectors usable at least "
                 f"half the time are usable (longest {z - a})")
        aman.restrict("samps", (aman.samps.offset + a, aman.samps.offset + z))
        kept += aman.dets.count
        used += aman.samps.count
        freqs_hz, pxx_w2_per_hz = fft_ops.calc_psd(aman, signal=aman.signal, nperseg=128)
        white = pxx_w2_per_hz[:, freqs_hz > 10.0]  # above the HWP and drift lines
        levels += np.sqrt(np.median(white, axis=1)).tolist()
    if not levels:
        fail(f"{out}: no detector usable at least half the time: no usable power in the recording?")
    report(args, {
        "observations": names,
        "detectors_kept": kept,
        "detectors_cut": cut,
        "samples_used": used,
        "signal_units": units,
        "sample_rate_hz": rate_hz,
        "white_noise_w_per_rthz_median": float(np.median(levels)),
    })


if __name__ == "__main__":
    main()

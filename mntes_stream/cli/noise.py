"""``mntes-stream noise RUN``: the white readout noise per channel, from a recording's counts."""

from __future__ import annotations

import sys

from mntes_stream.cli._common import add_quiet
from mntes_stream.options import number

HELP = "estimate the white readout noise per channel from a recording's counts (a dark run): a noise file"


def _gains(source, params_path):
    """|gain| (A per count) by detector id: from --params, else the recording's latest provenance."""
    import tomllib

    from mntes_stream.io.paramfile import load_params, parse_params

    if params_path:
        params = load_params(params_path)
    else:
        from mntes_stream.io.mcap import latest_provenance
        from mntes_stream.io.messages import decode

        raw = latest_provenance(source)
        params = {}
        if raw is not None:
            prov = decode(raw, "mntes.provenance")
            if prov.params_toml:
                params = parse_params(tomllib.loads(prov.params_toml), "recorded provenance")
    return {d: abs(complex(p.gain_a_per_count)) for d, p in params.items()}


def estimate(source, duration_s: float | None = None, params_path=None) -> dict:
    """The noise document of a recording (see ``io.noisefile``).

    Each counts chunk's samples are one contiguous stretch: second differences
    never cross a chunk boundary (a gap), and :func:`core.uncertainty.white_noise_counts`
    pools them per channel and quadrature.
    """
    import numpy as np

    from mntes_stream.core.ids import detector_id
    from mntes_stream.core.uncertainty import NOISE_FILE_FORMAT, module_key, white_noise_counts
    from mntes_stream.errors import ConfigError, SchemaError
    from mntes_stream.io.mcap import Session
    from mntes_stream.io.messages import decode

    session = Session(source, warn=False)
    start = session.start_ns
    end = None if duration_s is None or start is None else start + int(duration_s * 1e9)
    sums: dict[str, list] = {}  # id -> [sum of squares I, Q, count of second differences]
    rejected = 0
    for m in session.iter_messages("mntes/*/counts/*/*", end_ns=end):
        try:
            c = decode(m.payload, "mntes.counts")
        except SchemaError:
            rejected += 1
            continue
        if c.counts_i.shape[1] < 3:
            continue
        # Per chunk: sigma^2 times the number of differences, so chunks pool by their length.
        si, ni = white_noise_counts(c.counts_i)
        sq, nq = white_noise_counts(c.counts_q)
        for k, ch in enumerate(c.channels):
            acc = sums.setdefault(detector_id(c.board, c.module, int(ch)), [0.0, 0.0, 0, 0])
            if ni[k] and np.isfinite(si[k]):
                acc[0] += si[k] ** 2 * ni[k]
                acc[2] += int(ni[k])
            if nq[k] and np.isfinite(sq[k]):
                acc[1] += sq[k] ** 2 * nq[k]
                acc[3] += int(nq[k])
    if not sums:
        raise ConfigError(f"{source}: no counts chunks of 3 or more samples to estimate noise from")
    gains = _gains(source, params_path)
    channels, per_det, modules = {}, {}, {}
    for det, (s2i, s2q, n_i, n_q) in sorted(sums.items()):
        sig_i = float(np.sqrt(s2i / n_i)) if n_i else float("nan")
        sig_q = float(np.sqrt(s2q / n_q)) if n_q else float("nan")
        entry = {"sigma_counts_i": sig_i, "sigma_counts_q": sig_q, "second_differences": int(min(n_i, n_q))}
        # One number per quadrature: the converter's readout noise is the same on I and Q.
        sig = float(np.sqrt(np.nanmean([sig_i**2, sig_q**2]))) if (n_i or n_q) else float("nan")
        if det in gains and np.isfinite(sig):
            entry["readout_noise_a"] = per_det[det] = sig * gains[det]
            mk = module_key(det)
            if mk:
                modules.setdefault(mk, []).append(per_det[det])
        channels[det] = entry
    return {
        "format": NOISE_FILE_FORMAT, "version": 1, "source": str(source),
        "duration_s": duration_s,
        "estimator": "per chunk, second differences (var = 6 sigma^2), outliers beyond 6 robust sigma left out, "
                     "quantisation (1/12 count^2) removed; I and Q pooled; times |gain| of the parameters",
        "readout_noise_a": per_det,
        "by_module": {k: float(np.median(v)) for k, v in sorted(modules.items())},
        "channels": channels,
        "without_gain": sorted(d for d in channels if d not in per_det),
        "rejected_chunks": rejected,
    }


def run(args) -> int:
    import json
    from pathlib import Path

    from mntes_stream.errors import ConfigError
    from mntes_stream.io.noisefile import write_noise

    if args.duration is not None and not args.duration > 0:
        raise ConfigError(f"--duration must be > 0 seconds, got {args.duration}")
    if args.out and Path(args.out).exists() and not args.overwrite:
        raise ConfigError(f"{args.out} exists: give --overwrite to replace it")
    doc = estimate(args.run, args.duration, args.params)
    if args.out:
        write_noise(doc, args.out)
    if args.json:
        print(json.dumps(doc, indent=1))
        return 0
    # The summary is the result's last line: -q (no progress; noise has none) keeps it, as every command does.
    vals = list(doc["readout_noise_a"].values())
    rng = f"{min(vals):.3g}-{max(vals):.3g} A" if vals else "no gain known: counts only"
    print(f"noise: {len(doc['channels'])} channels, readout noise per quadrature {rng}, "
          f"{len(doc['by_module'])} modules" + (f"; wrote {args.out}" if args.out else ""), file=sys.stderr)
    if doc["without_gain"]:
        print(f"noise: {len(doc['without_gain'])} channels without parameters (no gain): counts only",
              file=sys.stderr)
    return 0


def register(sub) -> None:
    p = sub.add_parser("noise", help=HELP, description=HELP + ". The file is what a converter's "
                       "[uncertainty] noise_file reads (docs/uncertainty.md).")
    p.add_argument("run", metavar="RUN", help="recording: an .mcap file, a directory of them, or an `up` folder")
    p.add_argument("--out", metavar="FILE", help="write the noise file (JSON) here")
    p.add_argument("--duration", type=number(float, "s"), metavar="S", help="use only the first S seconds of the run")
    p.add_argument("--params", metavar="FILE", help="detector parameters for the gains (default: the recorded ones)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing --out file")
    p.add_argument("--json", action="store_true", help="print the whole noise document as JSON")
    add_quiet(p)
    p.set_defaults(func=run)

"""``mntes-stream simulate``: a simulated DfMux array, live over zenoh or into an MCAP file."""

from __future__ import annotations

import json
import sys

from mntes_stream.cli._common import add_zenoh_args, print_mapping
from mntes_stream.options import number

# The [simulator] settings the flags set, declared once (core.sim.SimConfig, service.simulator's config): types,
# ranges and help come from the declarations; the flags keep their spellings (--sample-rate, --f-hwp, --duration).
_SIM = ("boards", "modules", "channels", "sample_rate_hz", "seed")
_SERVICE = ("setup", "duration_s", "chunk_s", "speed")


def _config(args):
    """The ``[simulator]`` service config: ``--config``, then ``--set``, then the flags, as every service's
    (``cli._common.service_config``; ``--set`` needs no ``--config`` here: the defaults stand for the file)."""
    from pathlib import Path

    from mntes_stream.cli._common import settings_from_args, with_flags, zenoh_layer
    from mntes_stream.core.sim import HWP_FREQUENCIES_HZ
    from mntes_stream.service.config import apply_overrides, read_toml, with_zenoh
    from mntes_stream.service.simulator import SimulatorService

    doc = read_toml(args.config) if args.config else {}
    doc = apply_overrides(doc, [_table_key(item) for item in args.set or []], SimulatorService)
    where = args.config or "command line"
    base = str(Path(args.config).resolve().parent) if args.config else None
    cfg = SimulatorService.config_from_document(doc, where, base_dir=base)
    sim = settings_from_args(args, (*_SIM, "f_hwp_hz"))
    if args.telescope:
        sim["f_hwp_hz"] = HWP_FREQUENCIES_HZ[args.telescope]
    return with_zenoh(with_flags(cfg, {**settings_from_args(args, _SERVICE), "sim": sim}), zenoh_layer(args))


def _table_key(item: str) -> str:
    """``--set KEY=VALUE`` (the old spelling) as ``simulator.KEY=VALUE``, said once on stderr."""
    name = item.partition("=")[0]
    if "=" in item and "." not in name:
        print(f"mntes-stream: warning: --set {item}: KEY=VALUE is deprecated; use simulator.{item}", file=sys.stderr)
        return f"simulator.{item}"
    return item


def _refuse_inapplicable(args) -> None:
    """Options that would be ignored by this run: one ConfigError naming them."""
    from mntes_stream.errors import ConfigError

    wrong = []
    if args.out and args.speed is not None:
        wrong.append("--speed is for live publication (a file is written as fast as possible)")
    if not args.perturbed_params_out and (args.error_scale is not None or args.error_seed is not None):
        wrong.append("--error-scale/--error-seed need --perturbed-params-out")
    if args.no_truth and args.truth:
        wrong.append("--truth and --no-truth contradict each other")
    if wrong:
        raise ConfigError("; ".join(wrong))


def _refuse_g3_options(args) -> None:
    """G3-only options given without ``--format g3`` are an error, not ignored."""
    from mntes_stream.errors import ConfigError

    given = [flag for flag, value in (("--layout", args.layout), ("--exact-counts", args.exact_counts or None),
                                      ("--nuller-gain", args.nuller_gain), ("--gain-step", args.gain_step or None))
             if value is not None]
    if given:
        raise ConfigError(f"{', '.join(given)} apply to --format g3 only")


def run(args) -> int:
    from pathlib import Path

    from tqdm import tqdm

    from mntes_stream.cli._common import claim_out
    from mntes_stream.errors import ConfigError
    from mntes_stream.io.paramfile import dump_params
    from mntes_stream.service.simulator import (
        SimulatorSource,
        TruthRecorder,
        perturbed_params,
        run_simulator,
        write_mcap,
    )

    _refuse_inapplicable(args)
    svc = _config(args)
    if args.format == "g3":  # SPT-3G G3 file instead of MCAP/zenoh (mntes_stream.g3.sim)
        from mntes_stream.cli.g3 import run_simulate_g3

        return run_simulate_g3(args, svc)
    _refuse_g3_options(args)
    config, settings = svc.sim, svc.zenoh
    duration = svc.duration_s
    live = bool(settings.connect or settings.listen or settings.file)
    if bool(args.out) == live:
        raise ConfigError("simulate: give either --out FILE.mcap or zenoh endpoints (-e/--connect, -l/--listen, "
                          "-c/--zenoh-config or a [zenoh] table)")
    if args.out:
        claim_out(args.out, args.overwrite)
    source = SimulatorSource(config, svc.setup, svc.chunk_s)
    stem = Path(args.out).with_suffix("") if args.out else None
    params_out = args.params_out or (f"{stem}.params.toml" if stem else None)
    truth_out = None if args.no_truth else (args.truth or (f"{stem}.truth.npz" if stem else None))
    meta = {"source": "mntes-stream simulate (truth)", "sim_config": json.dumps(config.to_dict())}
    if params_out:
        dump_params(source.params, params_out, metadata=meta)
    if args.perturbed_params_out:
        scale, seed = 1.0 if args.error_scale is None else args.error_scale, args.error_seed or 0
        wrong = perturbed_params(source.params, scale, seed)
        dump_params(wrong, args.perturbed_params_out,
                    metadata={"source": f"mntes-stream simulate: truth with calibration errors x{scale} "
                                        f"(seed {seed})"})
    truth = TruthRecorder(source.detector_ids, config) if truth_out else None
    if args.out:
        n = source.n_chunks(duration)
        if n is None:
            raise ConfigError("simulate --out needs --duration > 0")
        with tqdm(total=n, desc="simulate", unit="chunk", disable=args.json or args.quiet or None) as bar:
            result = write_mcap(source, args.out, duration, truth=truth, progress=bar.update)
    else:
        if not args.quiet:
            print(f"simulate: {config.n_detectors} detectors on zenoh {list(settings.connect or ()) + list(settings.listen or ())}, "
                  f"setup {svc.setup!r}, {svc.speed:g}x real time" +
                  (f", {duration:g} s" if duration else ", until Ctrl-C"), file=sys.stderr)
        # The simulator service's lifecycle (what serve and up run): SIGINT/SIGTERM stop it, linger_s after.
        result = run_simulator(svc, truth=truth, source=source)
        result.pop("counts_published", None)  # the summary simulate has always printed
    if truth is not None:
        truth.save(truth_out)
    result.update({"detectors": config.n_detectors, "params": params_out, "truth": truth_out,
                   "perturbed_params": args.perturbed_params_out})
    print_mapping(result, args.json)
    return 0


def register(sub) -> None:
    from mntes_stream.cli._common import arguments

    p = sub.add_parser(
        "simulate", help="simulate a DfMux array: publish over zenoh or write an MCAP or G3 file (truth alongside)",
        description="Simulate a TES array read out by DfMux: publish it over zenoh (give zenoh endpoints) or write "
                    "--out FILE (MCAP, or a G3 run with --format g3). Writes the truth parameters (TOML) and the "
                    "per-sample truth (.npz, never read by a converter) next to the output.")
    arguments(p, _simulate_args)


def _simulate_args(p) -> None:
    from mntes_stream.cli._common import add_json, add_overwrite, add_quiet, add_settings_args, deprecated_alias

    p.add_argument("--config", metavar="TOML", help="service config with [simulator] and [zenoh] tables")
    p.add_argument("--out", metavar="FILE", help="write this file instead of publishing: an MCAP recording, or with "
                                                 "--format g3 a G3 run (RUN.g3)")
    deprecated_alias(p, "--mcap", "--out", dest="out")
    p.add_argument("--format", choices=("mcap", "g3"), default="mcap",
                   help="mcap (default); g3: write what a DfMux DAQ would (SPT-3G G3 file --out, see --layout)")
    from mntes_stream.cli.g3 import add_simulate_g3_args
    from mntes_stream.core.sim import SimConfig
    from mntes_stream.service.simulator import SimulatorServiceConfig

    add_simulate_g3_args(p)
    add_settings_args(p, SimulatorServiceConfig, ("setup",))
    add_settings_args(p, SimConfig, _SIM, spelled={"sample_rate_hz": "--sample-rate"}, metavars={"sample_rate_hz": "HZ"})
    hwp = p.add_mutually_exclusive_group()
    hwp.add_argument("--telescope", choices=["LFT", "MFT", "HFT"], help="HWP frequency of a LiteBIRD telescope")
    add_settings_args(hwp, SimConfig, ("f_hwp_hz",), spelled={"f_hwp_hz": "--f-hwp"}, metavars={"f_hwp_hz": "HZ"})
    add_settings_args(p, SimulatorServiceConfig, _SERVICE[1:], {"duration_s": ("--duration",)},
                      metavars={"duration_s": "S", "chunk_s": "S"})
    p.add_argument("--set", action="append", metavar="TABLE.KEY=VALUE", help="any simulator or zenoh setting "
                   "(repeatable; VALUE in TOML), e.g. --set simulator.jupiter_peak_w=0.3e-12 "
                   "--set simulator.latched_per_module=2")
    p.add_argument("--params-out", metavar="TOML", help="truth parameter file (default next to --out)")
    p.add_argument("--truth", metavar="NPZ", help="per-sample truth file (default next to --out)")
    p.add_argument("--no-truth", action="store_true", help="do not keep the per-sample truth")
    p.add_argument("--perturbed-params-out", metavar="TOML",
                   help="also write the truth with random calibration errors (for robustness studies)")
    p.add_argument("--error-scale", type=number(float, ge=0), help="--perturbed-params-out: calibration errors in units of the "
                                                     "assumed 1-sigma (default 1)")
    p.add_argument("--error-seed", type=number(int, ge=0), help="--perturbed-params-out: random seed of the calibration errors "
                                                  "(default 0)")
    add_overwrite(p, "replace an existing --out file")
    add_json(p)
    add_quiet(p)
    add_zenoh_args(p)
    p.set_defaults(func=run)

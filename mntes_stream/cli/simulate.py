"""``mntes-stream simulate``: a simulated DfMux array, live over zenoh or into an MCAP file."""

from __future__ import annotations

import json
import sys

from mntes_stream.cli._common import print_mapping


def _value(text: str):
    try:
        return json.loads(text)
    except json.JSONDecodeError:
        return text


def _config(args):
    """(SimConfig, ZenohSettings, run options) from ``--config`` and the command line (which wins)."""
    import dataclasses

    from mntes_stream.core.sim import HWP_FREQUENCIES_HZ, SimConfig
    from mntes_stream.errors import ConfigError
    from mntes_stream.io.transport import ZenohSettings

    settings: dict = {}
    zenoh = ZenohSettings()
    run: dict = {}
    if args.config:
        import tomllib
        from pathlib import Path

        from mntes_stream.service.simulator import SimulatorService

        try:
            doc = tomllib.loads(Path(args.config).read_text())
        except (OSError, tomllib.TOMLDecodeError) as exc:
            raise ConfigError(f"{args.config}: {exc}") from None
        svc = SimulatorService.from_dict(doc, args.config, base_dir=str(Path(args.config).parent))
        settings = svc.config.to_dict()
        zenoh = svc.zenoh
        run = {f.name: getattr(svc, f.name) for f in dataclasses.fields(svc) if f.name not in ("config", "zenoh")}
    for name, attr in (("boards", "boards"), ("modules", "modules"), ("channels", "channels"),
                       ("sample_rate_hz", "sample_rate"), ("seed", "seed")):
        if getattr(args, attr) is not None:
            settings[name] = getattr(args, attr)
    if args.telescope:
        settings["f_hwp_hz"] = HWP_FREQUENCIES_HZ[args.telescope]
    if args.f_hwp is not None:
        settings["f_hwp_hz"] = args.f_hwp
    for item in args.set or []:
        if "=" not in item:
            raise ConfigError(f"--set expects KEY=VALUE, got {item!r}")
        key, text = item.split("=", 1)
        settings[key.strip()] = _value(text)
    config = SimConfig.from_dict(settings)
    for name in ("setup", "chunk_s", "speed", "duration_s"):
        value = getattr(args, name)
        if value is not None:
            run[name] = value
    if args.connect:
        zenoh = dataclasses.replace(zenoh, connect=tuple(args.connect))
    if args.listen:
        zenoh = dataclasses.replace(zenoh, listen=tuple(args.listen))
    return config, zenoh, run


def run(args) -> int:
    from pathlib import Path

    from tqdm import tqdm

    from mntes_stream.errors import ConfigError
    from mntes_stream.io.paramfile import dump_params
    from mntes_stream.service.simulator import (
        SimulatorService,
        SimulatorSource,
        TruthRecorder,
        perturbed_params,
        publish_live,
        write_mcap,
    )

    config, settings, run_opts = _config(args)
    svc = SimulatorService(config, settings, **run_opts)  # validates; holds the defaults
    duration = svc.duration_s
    live = bool(settings.connect or settings.listen or settings.config_file)
    if bool(args.mcap) == live:
        raise ConfigError("simulate: give either --mcap FILE or zenoh endpoints (--connect/--listen or --config)")
    source = SimulatorSource(config, svc.setup, svc.chunk_s)
    stem = Path(args.mcap).with_suffix("") if args.mcap else None
    params_out = args.params_out or (f"{stem}.params.toml" if stem else None)
    truth_out = None if args.no_truth else (args.truth or (f"{stem}.truth.npz" if stem else None))
    meta = {"source": "mntes-stream simulate (truth)", "sim_config": json.dumps(config.to_dict())}
    if params_out:
        dump_params(source.params, params_out, metadata=meta)
    if args.perturbed_params_out:
        wrong = perturbed_params(source.params, args.error_scale, args.error_seed)
        dump_params(wrong, args.perturbed_params_out,
                    metadata={"source": f"mntes-stream simulate: truth with calibration errors x{args.error_scale} "
                                        f"(seed {args.error_seed})"})
    truth = TruthRecorder(source.detector_ids, config) if truth_out else None
    if args.mcap:
        n = source.n_chunks(duration)
        if n is None:
            raise ConfigError("simulate --mcap needs --duration > 0")
        with tqdm(total=n, desc="simulate", unit="chunk", disable=args.json or None) as bar:
            result = write_mcap(source, args.mcap, duration, truth=truth, progress=bar.update)
    else:
        from mntes_stream.service import stop_on_signals

        print(f"simulate: {config.n_detectors} detectors on zenoh {list(settings.connect) + list(settings.listen)}, "
              f"setup {svc.setup!r}, {svc.speed:g}x real time" + (f", {duration:g} s" if duration else ", until Ctrl-C"),
              file=sys.stderr)
        with stop_on_signals() as stop:
            result = publish_live(source, settings, speed=svc.speed, duration_s=duration, stop=stop, truth=truth,
                                  linger_s=svc.linger_s)
    if truth is not None:
        truth.save(truth_out)
    result.update({"detectors": config.n_detectors, "params": params_out, "truth": truth_out,
                   "perturbed_params": args.perturbed_params_out})
    print_mapping(result, args.json)
    return 0


def register(sub) -> None:
    p = sub.add_parser(
        "simulate", help="simulate a DfMux array: publish over zenoh or write an MCAP file (truth alongside)",
        description="Simulate a TES array read out by DfMux. Writes the truth parameters (TOML) and the "
                    "per-sample truth (.npz, never read by a converter) next to the output.")
    p.add_argument("--config", metavar="TOML", help="service config with [simulator] and [zenoh] tables")
    p.add_argument("--mcap", metavar="FILE", help="write an MCAP file instead of publishing")
    p.add_argument("--connect", action="append", metavar="ENDPOINT", help="zenoh endpoint to connect to (repeatable)")
    p.add_argument("--listen", action="append", metavar="ENDPOINT", help="zenoh endpoint to listen on (repeatable)")
    p.add_argument("--setup", help="setup name in the keys (default lab, as every service)")
    p.add_argument("--boards", type=int)
    p.add_argument("--modules", type=int, help="modules per board")
    p.add_argument("--channels", type=int, help="channels per module (DfMux: 64 or 128)")
    p.add_argument("--sample-rate", type=float, metavar="HZ", help="default 152.59 (19.1 is flight-like)")
    hwp = p.add_mutually_exclusive_group()
    hwp.add_argument("--telescope", choices=["LFT", "MFT", "HFT"], help="HWP frequency of a LiteBIRD telescope")
    hwp.add_argument("--f-hwp", type=float, metavar="HZ", help="HWP rotation frequency")
    p.add_argument("--seed", type=int)
    p.add_argument("--duration", dest="duration_s", type=float, metavar="S", help="seconds of data (live: 0 = forever)")
    p.add_argument("--chunk-s", type=float, metavar="S", help="chunk length (default 0.1 s)")
    p.add_argument("--speed", type=float, help="live: multiple of real time (0: as fast as possible)")
    p.add_argument("--set", action="append", metavar="KEY=VALUE", help="any simulator setting (repeatable), "
                   "e.g. --set jupiter_peak_w=0.3e-12 --set latched_per_module=2")
    p.add_argument("--params-out", metavar="TOML", help="truth parameter file (default next to --mcap)")
    p.add_argument("--truth", metavar="NPZ", help="per-sample truth file (default next to --mcap)")
    p.add_argument("--no-truth", action="store_true", help="do not keep the per-sample truth")
    p.add_argument("--perturbed-params-out", metavar="TOML",
                   help="also write the truth with random calibration errors (for robustness studies)")
    p.add_argument("--error-scale", type=float, default=1.0, help="calibration errors in units of the assumed 1-sigma")
    p.add_argument("--error-seed", type=int, default=0)
    p.add_argument("--json", action="store_true", help="print the result as JSON")
    p.set_defaults(func=run)

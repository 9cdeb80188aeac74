"""``mntes-stream g3-bridge`` and the G3 side of ``convert`` (SPT-3G readout in and out)."""

from __future__ import annotations

import contextlib
import dataclasses
import json
import tempfile
from pathlib import Path

from mntes_stream.cli._common import add_quiet, add_zenoh_args, arguments, print_mapping
from mntes_stream.options import number


def add_g3_convert_args(p) -> None:
    """``convert``'s options for G3 input or output (an error where they do not apply, never ignored)."""
    g = p.add_argument_group("G3 (SPT-3G)", "when IN or OUT is a .g3 file: RUN.g3 -> OUT.g3 appends MntesOpticalPower "
                                            "and MntesFlags to every Scan frame; RUN.g3 -> OUT.mcap converts through "
                                            "the live pipeline; REC.mcap -> OUT.g3 writes the power as Scan frames")
    g.add_argument("--kind", default=None, choices=("table", "grid", "exact", "linear", "electrical"),
                   help="RUN.g3 -> OUT.g3: converter kind (default table; electrical needs no --params: minus "
                        "spt3g's electrical power); REC.mcap -> OUT.mcap: instead of the recorded kind (or the "
                        "--config's [converter] kind), e.g. linear: the linear baseline of the same counts")
    g.add_argument("--wiring", metavar="RUN.g3", help="REC.mcap -> OUT.g3: a G3 file whose wiring map names the "
                                                      "bolometers (default: detector ids as names)")
    add_g3_input_args(g)
    g.add_argument("--setup", default=None, help="RUN.g3 -> OUT.mcap: the setup name of the messages (default lab)")
    g.add_argument("--scan-samples", type=number(int, ge=1), default=None, help="RUN.g3 -> OUT.g3 of raw Timepoints: samples per "
                                                                  "Scan frame (default 1000)")


def refuse_inapplicable(args, g3_in: bool, g3_out: bool) -> None:
    """Options given to a conversion they do not apply to: one ConfigError naming them."""
    from mntes_stream.errors import ConfigError

    applies = {"--kind": g3_in == g3_out, "--wiring": g3_out and not g3_in, "--t-bath-key": g3_in,
               "--t-bath-unit": g3_in, "--t-bath-default-k": g3_in, "--b-field-t": g3_in,
               "--setup": g3_in and not g3_out, "--scan-samples": g3_in and g3_out}
    given = [flag for flag, ok in applies.items() if getattr(args, flag[2:].replace("-", "_")) is not None and not ok]
    if given:
        what = {(True, True): "RUN.g3 -> OUT.g3", (True, False): "RUN.g3 -> OUT.mcap",
                (False, True): "REC.mcap -> OUT.g3", (False, False): "REC.mcap -> OUT.mcap"}[(g3_in, g3_out)]
        hint = "; the recorded converter kind is used" if "--kind" in given and not g3_in else ""
        raise ConfigError(f"{', '.join(given)} do{'es' if len(given) == 1 else ''} not apply to {what} "
                          f"(convert --help says which conversion takes which option){hint}")


# The [g3] settings a G3 file's reader takes from the command line (convert, params): flags, types, ranges and
# help from G3InputConfig's declarations.
_G3_INPUT = ("t_bath_key", "t_bath_unit", "t_bath_default_k", "b_field_t")
_G3_METAVARS = {"t_bath_key": "FRAME.ENTRY"}


def add_g3_input_args(p) -> None:
    """How a G3 file is read (``--t-bath-key``, ``--t-bath-unit``, ``--t-bath-default-k``, ``--b-field-t``)."""
    from mntes_stream.cli._common import add_settings_args
    from mntes_stream.g3.settings import G3InputConfig

    add_settings_args(p, G3InputConfig, _G3_INPUT, metavars=_G3_METAVARS)


def g3_input_config(args):
    """The G3InputConfig of the flags given (the declared defaults for the rest)."""
    from mntes_stream.cli._common import settings_from_args
    from mntes_stream.g3.settings import G3InputConfig

    return G3InputConfig(**settings_from_args(args, _G3_INPUT))


def quiet_spt3g() -> None:
    """The command says what went wrong in one line: spt3g's reader keeps its own error log to itself."""
    from mntes_stream.g3 import spt3g

    core, _ = spt3g()
    core.set_log_level(core.G3LogLevel.LOG_FATAL, "G3Reader")


def run_g3_convert(args, pipeline) -> int:
    from mntes_stream.errors import SchemaError
    from mntes_stream.g3 import spt3g_in_use

    quiet_spt3g()
    try:
        return _run_g3_convert(args, pipeline)
    except RuntimeError as exc:  # spt3g's own read errors (a frame it cannot decode): one line, with which spt3g
        raise SchemaError(f"{args.input}: spt3g cannot read it: {exc} [G3 on {spt3g_in_use()}]", "g3_read") from None


def _run_g3_convert(args, pipeline) -> int:
    from mntes_stream.errors import ConfigError
    from mntes_stream.g3 import files, spt3g_in_use

    g3_in, g3_out = files.is_g3(args.input), files.is_g3(args.output)
    if g3_out and getattr(args, "hk", None):
        raise ConfigError("--hk applies to MCAP output (RUN.g3 or REC.mcap -> OUT.mcap): OUT.g3 takes the bath "
                          "from the run's GcpSlow frames")
    if g3_in and g3_out:
        if args.tables:
            raise ConfigError("RUN.g3 -> OUT.g3 builds its converter from --params (and --kind); --tables is for MCAP")
        result = files.g3_to_g3(args.input, args.output, params=args.params, kind=args.kind or "table",
                                config=g3_input_config(args), scan_samples=args.scan_samples or 1000)
    elif g3_in:
        from mntes_stream.cli.ocs import hk_messages_of

        stats = files.g3_to_mcap(args.input, args.output, params=args.params, tables=args.tables,
                                 config=g3_input_config(args), setup=args.setup or "lab", pipeline_config=pipeline,
                                 progress=not (args.quiet or args.json),
                                 hk=hk_messages_of(args, args.setup or "lab"))  # --hk: bath from OCS HK files
        result = dataclasses.asdict(stats) | {"spt3g": spt3g_in_use()}
        if not args.json:
            print(stats.summary())
            if not args.quiet:
                print(f"  G3 read with {result['spt3g']}")
            return 0
    else:
        result = files.mcap_to_g3(args.input, args.output, params=args.params, tables=args.tables,
                                  wiring=args.wiring, pipeline_config=pipeline)
    result = dict(result) | {"spt3g": spt3g_in_use()}
    if args.json:
        print(json.dumps(result, indent=2, default=str))
    else:
        print_mapping(result, False)
    return 0


# The [g3-bridge] and [g3] settings the flags set (types, ranges and help from BridgeSettings and G3InputConfig);
# --hk and --t-bath-field are declared by add_hk_args (shared with convert and replay) and set the same settings.
_BRIDGE = ("source", "setup", "chunk_samples", "params", "boards", "duration_s")
_HK = ("hk", "t_bath_field")
_G3 = ("t_bath_key", "t_bath_default_k")
_SPELLED = {"source": "--from", "boards": "--board"}
_METAVARS = {"source": "tcp://HOST:PORT|RUN.g3", "boards": "SERIAL", "params": "FILE"}


def bridge_config(args):
    """The ``[g3-bridge]`` config the command line asks for (``--config``, ``--set``, flags, zenoh flags)."""
    from mntes_stream.cli._common import service_config, settings_from_args, zenoh_layer
    from mntes_stream.errors import ConfigError
    from mntes_stream.g3.bridge import G3BridgeService

    cfg = service_config(G3BridgeService, args.config, args.set,
                         {"bridge": settings_from_args(args, _BRIDGE + _HK), "g3": settings_from_args(args, _G3)},
                         zenoh_layer(args))
    if not cfg.bridge.source:
        raise ConfigError("g3-bridge: give the source (--from tcp://HOST:PORT or a G3 file, or source = in the config)")
    return cfg


def run_bridge(args) -> int:
    from mntes_stream.g3.bridge import G3BridgeService, ledger_line
    from mntes_stream.service.base import stop_on_signals

    cfg = bridge_config(args)
    quiet_spt3g()
    with stop_on_signals() as stop:
        result = G3BridgeService(cfg).start(stop=stop)
    from mntes_stream.g3 import spt3g_in_use

    result = dict(result) | {"spt3g": spt3g_in_use()}  # which spt3g read the frames
    if not args.quiet or args.json:
        print_mapping(result, args.json)
    if not args.json:
        print(ledger_line(result))  # the last line: what was published, missed and rejected
    return 0


def _bridge_args(p) -> None:
    from mntes_stream.cli._common import add_settings_args
    from mntes_stream.g3.bridge import BridgeSettings
    from mntes_stream.g3.settings import G3InputConfig

    p.add_argument("--config", metavar="FILE", help="bridge TOML ([g3-bridge], [g3], [zenoh]); flags override it")
    p.add_argument("--set", action="append", default=[], metavar="TABLE.KEY=VALUE", help="override a config value")
    add_settings_args(p, BridgeSettings, _BRIDGE, {"duration_s": ("--duration",)}, spelled=_SPELLED,
                      repeatable=("boards",), metavars=_METAVARS)
    add_settings_args(p, G3InputConfig, _G3, metavars=_G3_METAVARS)
    p.add_argument("--json", action="store_true", help="print the final statistics as one JSON document")
    add_quiet(p)
    from mntes_stream.cli.ocs import add_hk_args

    add_hk_args(p)  # --hk, --t-bath-field: the bath from OCS HK files instead of the DAQ's
    add_zenoh_args(p)


def register(sub) -> None:
    p = sub.add_parser("g3-bridge", help="publish SPT-3G DfMux readout (G3 over TCP or a G3 file) on zenoh",
                       description="Read G3 frames from a DAQ's G3NetworkSender (tcp://HOST:PORT) or a G3 file and "
                                   "publish counts, bias and bath-temperature housekeeping as the project's messages, "
                                   "so the converter, recorder and monitor run unchanged on real readout. Reconnects "
                                   "when the DAQ restarts; missing samples are counted.")
    arguments(p, _bridge_args)
    p.set_defaults(func=run_bridge)


def add_simulate_g3_args(p) -> None:
    """``simulate``'s options for ``--format g3`` (an error with ``--format mcap``, never ignored)."""
    g = p.add_argument_group("G3 output (--format g3)", "--out RUN.g3; beside it RUN.params.toml (keyed by detector "
                                                        "id, the DfMux gain of the run: the converter, g3-bridge "
                                                        "--params and convert take it as it is), "
                                                        "RUN.bolometer-params.toml (the truth keyed by bolometer name) "
                                                        "and RUN.truth.npz")
    g.add_argument("--layout", choices=("scans", "timepoints"), default=None,
                   help="collated Scan frames (spt3g's DfMuxCollator; default) or raw DAQ Timepoint frames")
    g.add_argument("--exact-counts", action="store_true",
                   help="scans: unrounded float64 counts (checks against the truth below DfMux count resolution)")
    g.add_argument("--nuller-gain", type=number(int, ge=0, le=15), default=None, help="DfMux nuller gain setting (0-15; default 2)")
    g.add_argument("--gain-step", action="append", default=[], metavar="S:GAIN",
                   help="the operator sets the nuller gain to GAIN at S seconds (repeatable)")


def run_simulate_g3(args, svc) -> int:
    from pathlib import Path

    from mntes_stream.cli._common import claim_out
    from mntes_stream.errors import ConfigError
    from mntes_stream.g3.files import write_converter_params
    from mntes_stream.g3.sim import write_g3
    from mntes_stream.service.simulator import TruthRecorder

    if not args.out:
        raise ConfigError("simulate --format g3 needs --out RUN.g3")
    if not svc.duration_s:
        raise ConfigError("simulate --format g3 needs --duration > 0")
    if args.perturbed_params_out:
        raise ConfigError("--perturbed-params-out applies to --format mcap only")
    steps = []
    for item in args.gain_step:
        t, _, g = item.partition(":")
        try:
            steps.append((float(t), int(g)))
        except ValueError:
            raise ConfigError(f"--gain-step expects S:GAIN, e.g. 60:5, got {item!r}") from None
    claim_out(args.out, args.overwrite)
    stem = Path(args.out)
    stem = stem.with_name(stem.name[:-3] if stem.name.endswith(".g3") else stem.name)
    params_out = args.params_out or f"{stem}.params.toml"
    bolometer_params = f"{stem}.bolometer-params.toml"
    truth_out = None if args.no_truth else (args.truth or f"{stem}.truth.npz")
    truth = TruthRecorder([], svc.sim) if truth_out else None  # ids set below: bolometer names
    quiet_spt3g()
    result = write_g3(svc.sim, args.out, svc.duration_s, layout=args.layout or "scans", truth=truth,
                      exact_counts=args.exact_counts, nuller_gain=2 if args.nuller_gain is None else args.nuller_gain,
                      gain_steps=steps, params_out=bolometer_params)
    # The converter's file: keyed by detector id, the gain the run's housekeeping gives (no Python needed).
    write_converter_params(args.out, bolometer_params, params_out)
    if truth is not None:
        from mntes_stream.core.ids import parse_detector_id
        from mntes_stream.core.sim import ArraySimulator
        from mntes_stream.g3.sim import bolometer_name

        truth.detector_ids = tuple(bolometer_name(*parse_detector_id(d)) for d in ArraySimulator(svc.sim).detector_ids)
        truth.save(truth_out)
    result.update({"params": params_out, "bolometer_params": bolometer_params, "truth": truth_out})
    print_mapping(result, args.json)
    return 0


@contextlib.contextmanager
def g3_sessions_as_mcap(args):
    """``export``: G3 inputs in ``args.session`` replaced by one temporary MCAP recording converted from them."""
    from mntes_stream.g3.files import is_g3

    g3 = [s for s in args.session if is_g3(s)]
    if not g3:
        yield args
        return
    from mntes_stream.errors import ConfigError

    if len(g3) != len(args.session):
        raise ConfigError("export: give either G3 files or MCAP recordings, not both")
    if not args.g3_params:
        raise ConfigError("export of a G3 run: give --g3-params FILE (detector parameters to convert it with)")
    from mntes_stream.g3 import isolated

    # Read in a child process on spt3g 1.0.2: this process may load a framework (so3g, toast) next.
    with tempfile.TemporaryDirectory(prefix="mntes-export-g3-") as tmp:
        out = Path(tmp) / "converted.mcap"
        isolated.run("g3_to_mcap", inputs=[str(g) for g in g3], output=str(out),
                     params=str(Path(args.g3_params).resolve()), setup=args.setup or "lab")
        args.session = [str(out)]
        yield args

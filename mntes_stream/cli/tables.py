"""``mntes-stream tables build|info``: response tables for a parameter file."""

from __future__ import annotations

from mntes_stream.cli._common import add_json, add_overwrite, add_quiet, print_mapping
from mntes_stream.options import number

# Options of one table kind only: given with the other kind they are an error (docs/cli.md).
_KIND_OPTIONS = {"table": ("p_tol_w",), "grid": ("bias_frac", "n_b_nodes", "n_power")}


def _build(args) -> int:
    from tqdm import tqdm

    from mntes_stream.cli._common import claim_out
    from mntes_stream.core.tables import TableDomain, build_bank
    from mntes_stream.io.paramfile import load_params
    from mntes_stream.io.tablefile import save_bank

    other = [f"--{n.replace('_', '-')}" for k, names in _KIND_OPTIONS.items() if k != args.kind for n in names
             if getattr(args, n) is not None]
    if other:
        from mntes_stream.errors import ConfigError

        raise ConfigError(f"{', '.join(other)}: not for --kind {args.kind}")
    claim_out(args.out, args.overwrite, inputs=[args.params])
    params = load_params(args.params)
    domain = TableDomain(
        p_opt_w=tuple(args.p_opt_w), t_bath_k=tuple(args.t_bath_k),
        b_field_t=tuple(args.b_field_t), v_frac=tuple(args.v_frac),
    )
    options = {}
    own = _KIND_OPTIONS[args.kind]
    for name in own:  # given, else the default of the kind's builder
        if getattr(args, name) is not None:
            value = getattr(args, name)
            options[name] = tuple(value) if isinstance(value, list) else value
    with tqdm(total=len(params), unit="det", desc=f"tables ({args.kind})", disable=args.quiet) as bar:
        bank = build_bank(params, kind=args.kind, domain=domain, progress=bar.update, **options)
    save_bank(bank, args.out)
    print(f"wrote {args.out}: {len(bank)} detectors, {bank.nbytes / 2**20:.1f} MiB, identity {bank.identity}")
    return 0


def _info(args) -> int:
    from mntes_stream.io.tablefile import load_bank

    summary = load_bank(args.file).summary()
    print_mapping(summary, args.json, width=20)
    return 0


def register(sub) -> None:
    p = sub.add_parser("tables", help="build or inspect response tables (one file per array)")
    tsub = p.add_subparsers(dest="tables_command", metavar="ACTION", required=True)
    b = tsub.add_parser("build", help="build the response tables of every detector in a parameter file")
    b.add_argument("--params", required=True, metavar="FILE", help="detector parameter file (TOML)")
    b.add_argument("--out", required=True, metavar="FILE", help="table file to write (.npz)")
    b.add_argument("--kind", choices=("table", "grid"), default="table",
                   help="table: structured, exact in environment (default); grid: the paper's route")
    b.add_argument("--p-opt-w", nargs=2, type=number(float, "W", ge=0), default=(0.0, 1.2e-12), metavar=("LO", "HI"),
                   help="optical power range to cover (W)")
    b.add_argument("--t-bath-k", nargs=2, type=number(float, "K", gt=0), default=(0.090, 0.110), metavar=("LO", "HI"),
                   help="bath temperature range to cover (K; default 0.090 0.110)")
    b.add_argument("--b-field-t", nargs=2, type=number(float, "T"), default=(-2e-4, 2e-4), metavar=("LO", "HI"),
                   help="magnetic field range to cover (T; default -2e-4 2e-4)")
    b.add_argument("--v-frac", nargs=2, type=number(float, gt=0), default=(0.9, 1.1), metavar=("LO", "HI"),
                   help="bias range relative to each detector's nominal")
    b.add_argument("--p-tol-w", type=number(float, "W", gt=0), help="table: interpolation tolerance in power (W; default 1e-20)")
    b.add_argument("--bias-frac", nargs="+", type=number(float, gt=0),
                   help="grid: discrete bias states relative to nominal (default 0.95 1.0 1.05)")
    b.add_argument("--n-b-nodes", type=number(int, ge=4), help="grid: uniform B nodes across --b-field-t (default 7)")
    b.add_argument("--n-power", type=number(int, ge=8), help="grid: knots per detector (default 256)")
    add_overwrite(b, "replace an existing --out file")
    add_quiet(b)
    b.set_defaults(func=_build)
    i = tsub.add_parser("info", help="describe a table file (verifies its hash)")
    i.add_argument("file", metavar="FILE", help="table file (.npz)")
    add_json(i, "print one JSON object")
    i.set_defaults(func=_info)

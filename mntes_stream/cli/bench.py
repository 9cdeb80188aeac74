"""``mntes-stream bench NAME [--json]``: run one benchmark and print its figures."""

from __future__ import annotations

import importlib
import pkgutil

from mntes_stream.cli._common import arguments, print_mapping


def _benches():
    import mntes_stream.bench as pkg

    for info in sorted(pkgutil.iter_modules(pkg.__path__), key=lambda m: m.name):
        if not info.name.startswith("_"):
            yield info.name, importlib.import_module(f"mntes_stream.bench.{info.name}")


def _run(args) -> int:
    from mntes_stream.bench import machine

    result = args.bench_module.run(args)
    result.setdefault("machine", machine())
    print_mapping(result, args.json, width=32)
    return 0


def _bench_args(p) -> None:
    bsub = p.add_subparsers(dest="bench", metavar="NAME", required=True)
    for name, module in _benches():
        # a module convert_offline is the bench convert-offline (flags are spelled with hyphens too)
        bp = bsub.add_parser(name.replace("_", "-"), help=getattr(module, "HELP", ""))
        bp.add_argument("--json", action="store_true", help="print one JSON object")
        module.add_arguments(bp)
        bp.set_defaults(func=_run, bench_module=module)


def register(sub) -> None:
    p = sub.add_parser("bench", help="benchmarks (speed, memory, accuracy)")
    arguments(p, _bench_args)  # every benchmark's module, imported for its flags: `bench` alone needs them

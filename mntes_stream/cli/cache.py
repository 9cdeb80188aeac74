"""``mntes-stream cache``: what the user's cache holds, and clearing it."""

from __future__ import annotations

HELP = "show the user's cache (table banks, converters as built, compiled kernels) and its size cap; --clear empties it"


def run(args) -> int:
    import json

    from mntes_stream import cache_root
    from mntes_stream.io.cache import DEFAULT_MAX_MB, PARTS, clear, usage

    if args.clear:
        parts = tuple(PARTS) if args.clear == "all" else (args.clear,)
        freed = clear(parts)
        print(f"cleared {', '.join(parts)} of {cache_root()}: {freed / 1e6:.1f} MB freed")
        return 0
    parts = usage()
    if args.json:
        print(json.dumps({"root": cache_root(), "table_cache_max_mb": DEFAULT_MAX_MB,
                          "parts": [p.__dict__ for p in parts]}, indent=2))
        return 0
    print(f"cache {cache_root()} ($MNTES_STREAM_CACHE, else $XDG_CACHE_HOME/mntes-stream or ~/.cache/mntes-stream):")
    for p in parts:
        print(f"  {p.name + '/':8} {p.bytes / 1e6:8.1f} MB in {p.files:4d} file(s): {p.what}")
    print(f"  total    {sum(p.bytes for p in parts) / 1e6:8.1f} MB; tables/ is pruned to {DEFAULT_MAX_MB:g} MB after "
          f"each write, least recently used first ([converter] table_cache_max_mb)")
    return 0


def register(sub) -> None:
    p = sub.add_parser("cache", help=HELP, description=HELP + ". Everything in it is rebuilt when needed.")
    p.add_argument("--clear", nargs="?", const="all", choices=("all", "tables", "numba"),
                   help="delete that part (default: all); the next start rebuilds it")
    p.add_argument("--json", action="store_true", help="print the parts as JSON")
    p.set_defaults(func=run)

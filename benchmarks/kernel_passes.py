"""Where the "table" kernel's time goes: its three passes over a row, each taken out in turn.

``core/_kernels.py``'s ``_table_kernel`` runs a row in three passes: the front end (counts to R and flags,
vector lanes), the table lookup (interval and its cubics, sample by sample) and the power (vector lanes).
This script makes variants of the module with a part replaced by something trivial (the output is then
wrong, which is the point: only the time is read), compiles each (not cached), and times each against the
unchanged kernel on ``bench convert``'s block (512 detectors x 10,000 samples), alternated in one process,
CPU time, median of ``--repeat``. What a part costs is the unchanged kernel's time less the variant's::

    python benchmarks/kernel_passes.py --json
    python benchmarks/kernel_passes.py --json --no-parts --against ../old/mntes_stream/core/_kernels.py

``--against``: another copy of the module (an older commit's, a worktree's) timed the same way, with
whether its power and flags equal this one's bit for bit.
A variant whose anchor text is no longer in the kernel (the kernel changed) is reported as such and skipped.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from mntes_stream.bench import convert as bench_convert
from mntes_stream.core import _kernels
from mntes_stream.core.convert import make_converter
from mntes_stream.core.tables import build_bank

_I = " " * 20  # the lookup loop's body, inside the row loop
_LOOKUP_START = f"{_I}rc = s_rc[s]\n{_I}j = k0 + cidx[np.uint64(c)]\n"
_LOOKUP_END = "                if not low_on:\n                    for s in range(n_samp):"
_STEP = (f"{_I}if (j + 1 < last) & (rc >= x[np.uint64(j + 1)]):\n"
         f"{_I}    j += 1\n"
         f"{_I}    marks[s] = (j + 1 < last) & (rc >= x[np.uint64(j + 1)])\n"
         f"{_I}else:\n"
         f"{_I}    marks[s] = 0\n")
_POWER = "p, beyond, _, _ = _lane_power(s_w[s], s_its[s], s_r[s], s_m2[s], tbs, bs, vs, q)"


def _no_lookup(src: str) -> str:
    a, b = src.index(_LOOKUP_START), src.index(_LOOKUP_END)
    return src[:a] + f"{_I}rc = s_rc[s]\n{_I}s_w[s] = rc * 1.5\n{_I}s_its[s] = rc + 2.0\n{_I}marks[s] = 0\n" + src[b:]


def _only_cell_read(src: str) -> str:
    a, b = src.index(_LOOKUP_START), src.index(_LOOKUP_END)
    return src[:a] + _LOOKUP_START + f"{_I}marks[s] = 0\n{_I}s_w[s] = rc * 1.5 + j\n{_I}s_its[s] = rc + 2.0\n" + src[b:]


def _replace(old: str, new: str):
    def edit(src: str) -> str:
        if old not in src:
            raise KeyError(old)
        return src.replace(old, new, 1)
    return edit


# name -> (what is taken out, edit of the module's source)
VARIANTS = {
    "no_power": ("the power pass's arithmetic (series, Joule term)",
                 _replace(_POWER, "p, beyond = s_w[s] * s_its[s] + s_r[s], False")),
    "no_lookup": ("the whole lookup pass (cell, interval step, cubics)", _no_lookup),
    "cell_only": ("the lookup's interval step and cubics (its cell read stays)", _only_cell_read),
    "branchless_step": ("the branch around the step (put back: the step as arithmetic, as before 2026-11-29)",
                        _replace(_STEP, f"{_I}j += (j + 1 < last) & (rc >= x[np.uint64(j + 1)])\n"
                                        f"{_I}marks[s] = (j + 1 < last) & (rc >= x[np.uint64(j + 1)])\n")),
    "no_step": ("the lookup's interval step (the compare with the next knot; one interval per cell)",
                _replace(_STEP, f"{_I}marks[s] = 0\n")),
}


def _variant(name: str, src: str, where: Path):
    path = where / f"kernel_variant_{name}.py"
    path.write_text(src.replace("cache=True", "cache=False"))
    spec = importlib.util.spec_from_file_location(path.stem, path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[path.stem] = mod
    spec.loader.exec_module(mod)
    return mod


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeat", type=int, default=7, help="timed calls of each kernel (median; default 7)")
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--against", type=Path, help="another core/_kernels.py to time against this one")
    ap.add_argument("--no-parts", action="store_true", help="skip the variants that take a part out")
    args = ap.parse_args()

    params = bench_convert.synthetic_params(512, seed=3)
    ids, ci, cq, env = bench_convert.synthetic_block(params, 10_000, seed=4)
    conv = make_converter("table", None, bank=build_bank(params, kind="table"), backend="numba")
    got = {}
    real = _kernels.table_numba

    def capture(*a, **kw):
        got["args"] = a
        return real(*a, **kw)

    _kernels.table_numba = capture
    try:
        out = conv.convert(ids, ci, cq, env)
    finally:
        _kernels.table_numba = real
    base_args = got["args"]
    src = Path(_kernels.__file__).read_text()
    kernels, skipped = {"unchanged": _kernels}, {}
    with tempfile.TemporaryDirectory() as tmp:
        for name, (_, edit) in ({} if args.no_parts else VARIANTS).items():
            try:
                kernels[name] = _variant(name, edit(src), Path(tmp))
            except (KeyError, ValueError):
                skipped[name] = "its anchor is no longer in core/_kernels.py"
        if args.against is not None:
            kernels["against"] = _variant("against", args.against.read_text(), Path(tmp))
        outputs = {name: (np.empty(ci.shape), np.empty(ci.shape, dtype=np.uint16)) for name in kernels}
        for name, mod in kernels.items():
            mod.table_numba(*base_args[:-2], *outputs[name])  # compiled here, not timed
        same = bool(np.array_equal(outputs["unchanged"][0], out.p_opt_w, equal_nan=True))
        times = {name: [] for name in kernels}
        for _ in range(args.repeat):
            for name, mod in kernels.items():
                c0 = time.process_time()
                mod.table_numba(*base_args[:-2], *outputs[name])
                times[name].append(time.process_time() - c0)
    med = {name: float(np.median(t)) for name, t in times.items()}
    whole = med["unchanged"]
    result = {
        "machine": f"{platform.machine()} {platform.processor() or ''}".strip(),
        "python": platform.python_version(),
        "block": list(ci.shape),
        "unchanged_ms": whole * 1e3,
        "unchanged_msamples_per_cpu_s": ci.size / whole / 1e6,
        "unchanged_equals_converter": same,
        "variants": {name: {"takes_out": VARIANTS[name][0], "ms": med[name] * 1e3,
                            "part_ms": (whole - med[name]) * 1e3, "part_fraction": (whole - med[name]) / whole}
                     for name in kernels if name in VARIANTS},
        "skipped": skipped,
    }
    if args.against is not None:
        p, f = outputs["against"]
        result["against"] = {"path": str(args.against), "ms": med["against"] * 1e3,
                             "speedup_of_this": med["against"] / whole,
                             "power_and_flags_bit_for_bit": bool(np.array_equal(p.view(np.int64),
                                                                                outputs["unchanged"][0].view(np.int64))
                                                                 and np.array_equal(f, outputs["unchanged"][1])),
                             "times_ms": [t * 1e3 for t in times["against"]],
                             "this_times_ms": [t * 1e3 for t in times["unchanged"]]}
    if args.json:
        print(json.dumps(result, indent=2))
        return
    print(f"unchanged kernel: {whole * 1e3:.1f} ms ({result['unchanged_msamples_per_cpu_s']:.1f} M samples per CPU s)")
    for name, v in result["variants"].items():
        print(f"  {name:10s} {v['ms']:6.1f} ms: {v['takes_out']} costs {v['part_ms']:5.1f} ms "
              f"({100 * v['part_fraction']:.0f} %)")
    for name, why in skipped.items():
        print(f"  {name}: skipped ({why})")
    if args.against is not None:
        a = result["against"]
        print(f"  against {a['path']}: {a['ms']:.1f} ms, this one {a['speedup_of_this']:.3f}x as fast, "
              f"bit for bit: {a['power_and_flags_bit_for_bit']}")


if __name__ == "__main__":
    main()

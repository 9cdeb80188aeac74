"""``bench stream --find-rate``: the real-time rate, the highest offered rate the pipeline sustains.

A trial offers the array (``--modules`` x ``--channels``) at one sample rate in
real time for ``--warmup`` + ``--sustain`` seconds through source, converter and
recorder (a fresh set of processes, no passthrough), and passes when, over the
sustained part, no chunk was lost, shed or set aside (late) and the p99 latency
(power published minus counts published) is below ``--p99-ms``. The rates are
bisected between the highest passing and the lowest failing, starting at half
the first upper bound: 1.05 x the flat-out pipeline rate of the run before
(when it ran flat out; real time cannot do better) or the passthrough's. No trial starts that would not end within ``--budget-s``, and at most
``--trials`` run.
"""

from __future__ import annotations

import copy
import sys
import time


def trial_passes(res: dict, p99_ms: float) -> tuple[bool, str]:
    """Whether one real-time run sustained its rate, and why not (one short phrase)."""
    why = []
    if not res.get("all_services_ok"):
        why.append(f"a service failed ({', '.join(res.get('failed_services') or ['?'])})")
    if res.get("lost"):
        why.append(f"lost {res['lost']}")
    for key in ("converter_shed", "converter_late"):
        if res.get(key):
            why.append(f"{key.split('_')[1]} {res[key]}")
    p99 = res.get("latency_p99_ms")
    if p99 is None or not p99 < p99_ms:  # nan (no latencies) fails too
        why.append(f"p99 {p99} ms")
    return not why, ", ".join(why)


def next_rate(lo: float, hi: float, tolerance: float) -> float | None:
    """The next rate to try between the highest passing ``lo`` (0: none yet) and lowest failing ``hi``.

    None once they are within ``tolerance`` of ``hi``. Without a passing rate
    yet, halve (a pipeline far below its flat-out rate is found in few trials).
    """
    if hi <= 0 or (lo > 0 and (hi - lo) / hi <= tolerance):
        return None
    if lo <= 0:
        return hi / 2
    return (lo + hi) / 2


def find_rate(args, first: dict, run_once, clock=time.monotonic, say=None) -> dict:
    """Bisect offered rates in real time; returns the search (every trial) and the rate found.

    Parameters
    ----------
    args : argparse.Namespace
        ``bench stream``'s arguments (copied per trial, rate set by ``sample_rate``).
    first : dict
        The run before: its flat-out rate bounds the search, its passthrough is the yardstick.
    run_once : callable(args) -> dict
        One run (``bench stream`` passes its own :func:`~mntes_stream.bench.stream.run_once`).
    """
    from mntes_stream.errors import ConfigError

    if say is None:
        def say(line):
            print(line, file=sys.stderr, flush=True)
    if args.sustain <= 0 or args.budget_s <= 0 or args.trials < 1 or not 0 < args.tolerance < 1:
        raise ConfigError("--find-rate takes --sustain > 0, --budget-s > 0, --trials >= 1 and 0 < --tolerance < 1")
    n_ch = args.modules * args.channels
    passthrough = first.get("passthrough_msamples_per_s") or 0.0
    # Flat out the pipeline cannot do more than it did; otherwise start from the passthrough.
    hi = first["msamples_per_s"] * 1.05 if first.get("mode") == "flat-out" else passthrough
    if hi <= 0:
        raise ConfigError("--find-rate: the first run gave no rate to start from")
    t0 = clock()
    lo, best, trials, hi_failed = 0.0, None, [], False
    trial_s = None  # wall seconds of one trial, learnt from the first
    rate = next_rate(lo, hi, args.tolerance)
    while rate is not None and len(trials) < args.trials:
        left = args.budget_s - (clock() - t0)
        need = trial_s if trial_s is not None else args.sustain + args.warmup + 30
        if need > left:
            say(f"find-rate: stopping, {left:.0f} s of the budget left and a trial takes about {need:.0f} s")
            break
        targs = copy.copy(args)
        targs.flat_out, targs.find_rate, targs.keep, targs.passthrough_s = False, False, None, 0.0
        targs.sample_rate = rate * 1e6 / n_ch
        targs.duration = args.warmup + args.sustain
        say(f"find-rate: trial {len(trials) + 1}: {rate:.3f} M samples/s ({targs.sample_rate:.1f} Hz) for "
            f"{args.sustain:g} s ...")
        ts = clock()
        res = run_once(targs)
        trial_s = clock() - ts
        ok, why = trial_passes(res, args.p99_ms)
        trials.append({"offered_msamples_per_s": round(rate, 4), "sample_rate_hz": round(targs.sample_rate, 3),
                       "passed": ok, "why_not": why, "wall_s": round(trial_s, 1),
                       **{k: res.get(k) for k in ("msamples_per_s", "latency_p50_ms", "latency_p99_ms",
                                                   "latency_max_ms", "lost", "converter_shed", "converter_late",
                                                   "cores_during_stream", "recorder_msamples_per_cpu_s",
                                                   "converter_msamples_per_core_s", "load_average_1min")}})
        say(f"find-rate: trial {len(trials)}: {'sustained' if ok else 'not sustained: ' + why} "
            f"(p99 {res.get('latency_p99_ms')} ms, {trial_s:.0f} s; {clock() - t0:.0f} s of {args.budget_s:g})")
        if ok:
            lo, best = rate, res
        else:
            hi, hi_failed = rate, True
        rate = next_rate(lo, hi, args.tolerance)
    found = lo if best is not None else None
    return {
        "criterion": f"0 lost, 0 shed, 0 late, p99 < {args.p99_ms:g} ms over {args.sustain:g} s, recorder on",
        "msamples_per_s": round(found, 4) if found else None,
        "sample_rate_hz": round(found * 1e6 / n_ch, 3) if found else None,
        # None when every trial passed: the bound was the flat-out rate, never tried in real time
        "lowest_failing_msamples_per_s": round(hi, 4) if hi_failed else None,
        "ratio_to_passthrough": round(found / passthrough, 3) if found and passthrough else None,
        "ratio_to_flat_out_pipeline": round(found / first["msamples_per_s"], 3)
        if found and first.get("mode") == "flat-out" and first.get("msamples_per_s") else None,
        "latency_p99_ms": best.get("latency_p99_ms") if best else None,
        "trials": trials,
        "search_wall_s": round(clock() - t0, 1),
    }

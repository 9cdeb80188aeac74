"""The monitor as a terminal table (``mntes-stream monitor --text``): pure formatting."""

from __future__ import annotations

import datetime as _dt

from mntes_stream.monitor.aggregate import STATE_NAMES, Aggregator
from mntes_stream.monitor.ledger_view import COLUMNS

__all__ = ["freshness_text", "ledger_lines", "leakage_lines", "render_text"]


def _f(v, fmt: str = "{:.1f}") -> str:
    return "-" if v is None else fmt.format(v)


def freshness_text(fr: dict) -> str:
    """The badge as words: LIVE, SHEDDING (with the counts), LAGGING, REPLAY (with the recording's time),
    STALE with the age, or WAITING."""
    if fr["state"] == "shedding":
        sh = fr["shedding"]
        return (f"SHEDDING: {', '.join(sh['services'])} shed {sh['shed']:,} chunks, {sh['set_aside']:,} set aside "
                "(overload: late power follows; offline convert gives what was shed)")
    if fr["state"] == "lagging":
        why = f"behind: {fr['behind']}" if fr.get("behind") else "a replay through a converter, or a process behind"
        return f"LAGGING: data {fr['lag_s']:.1f} s old on arrival (> {fr['lagging_after_s']:g} s: {why})"
    if fr["state"] == "waiting":
        return "WAITING: no power received yet"
    if fr["state"] == "stale":
        return (f"STALE: no data for {fr['age_s']:.1f} s (> {fr['threshold_s']:.2f} s = "
                f"{fr['stale_chunks']:g} chunk intervals of {fr['chunk_interval_s']:.3f} s)")
    if fr["state"] == "replay":
        t = fr["newest_t_ns"]
        rec = "-" if t is None else _dt.datetime.fromtimestamp(t / 1e9, _dt.UTC).strftime("%Y-%m-%d %H:%M:%S UTC")
        return f"REPLAY: recorded {rec}, latency on the recording's clock (newest {fr['age_s']:.1f} s ago)"
    return f"LIVE (newest data {fr['age_s']:.1f} s ago)"


def render_text(agg: Aggregator, tick: dict, max_listed: int = 12) -> str:
    """One screen: rates, latency, housekeeping, channel states and the channels not in transition.

    Parameters
    ----------
    agg : Aggregator
        After ``tick = agg.tick(now)`` (the caller holds the lock).
    tick : dict
    max_listed : int
        Channels listed at most (the count of the rest is given): the table stays bounded.
    """
    h = tick["health"]
    mon = h["monitor"]
    when = _dt.datetime.fromtimestamp(tick["t_ns"] / 1e9, _dt.UTC).strftime("%H:%M:%S UTC")
    lines = [f"mntes-stream monitor  {when}  channels {mon['channels']} in {mon['modules']} modules  "
             + freshness_text(tick["freshness"])]
    lines.append(f"{'source':<12}{'in/s':>8}{'out/s':>8}{'Msamp/s':>9}{'lat p50':>9}{'p99':>8}{'max ms':>8}"
                 f"{'lost':>6}{'shed':>6}{'late':>6}{'pend':>6}{'hk stale':>10}{'bad':>5}{'age s':>7}")
    for s in h["services"]:
        flags = ("  STALE" if s['stale'] else "") + ("  SHEDDING" if s.get("shedding") else "")
        lines.append(
            f"{s['service'][:11]:<12}{_f(s['in_chunks_per_s']):>8}{_f(s['out_chunks_per_s']):>8}"
            f"{_f(s['out_msamples_per_s'], '{:.3f}'):>9}{_f(s['latency_p50_ms']):>9}{_f(s['latency_p99_ms']):>8}"
            f"{_f(s['latency_max_ms']):>8}{s['chunks_lost']:>6}{s.get('chunks_shed', 0):>6}{s.get('chunks_late', 0):>6}"
            f"{s['chunks_pending']:>6}{s['hk_stale_samples']:>10}{s['bad_messages']:>5}{_f(s['age_s']):>7}{flags}"
        )
    bad = sum(mon["bad_messages"].values())
    lines.append(
        f"{'monitor':<12}{_f(mon['chunks_per_s']):>8}{'':>8}{_f(mon['msamples_per_s'], '{:.3f}'):>9}"
        f"{_f(mon['latency_p50_ms']):>9}{'':>8}{_f(mon['latency_max_ms']):>8}{mon['lost_chunks']:>6}"
        f"{'':>6}{'':>10}{bad:>5}   dropped {mon['dropped']}"
    )
    lines.extend(ledger_lines(h["services"], max_listed))
    hk = []
    for name, s in h["hk"].items():
        if s["value"] is None:
            value = "-"
        elif name == "t_bath":
            value = f"{s['value'] * 1e3:.4f} mK"
        else:
            value = f"{s['value'] * 1e6:.3f} uT"
        hk.append(f"{name} {value} (age {_f(s['age_s'])} s{', STALE' if s['stale'] else ''})")
    lines.append("housekeeping: " + "   ".join(hk))
    lines.append("states: " + "  ".join(f"{n} {tick['state_counts'][n]}" for n in STATE_NAMES))
    lines.extend(leakage_lines(tick.get("leakage") or {}, max_listed))
    listed, total = agg.channels_not_in_transition(max_listed)
    if total:
        more = f" (+{total - len(listed)} more)" if total > len(listed) else ""
        lines.append("not in transition: " + ", ".join(f"{d} {s}" for d, s in listed) + more)
    return "\n".join(lines)


_HEADS = {"converted": "conv", "late": "late", "shed": "shed", "rejected": "rej", "duplicate": "dup",
          "never_received": "never", "lost": "lost", "pending": "pend"}


def ledger_lines(services: list[dict], max_listed: int = 12) -> list[str]:
    """Each converter's ledger: its one-line summary, then its streams (lossy ones first, ``max_listed`` at most)."""
    out = []
    for s in services:
        led = s.get("ledger")
        if not led:
            continue
        out.append(f"ledger {s['service']}: {led['line']}")
        for line in (led.get("conflict_line"), led.get("began_line")):
            if line:
                out.append(f"  {line}")
        rows = led["streams"][:max_listed]
        if not rows:
            continue
        out.append("  " + f"{'stream':<10}" + "".join(f"{_HEADS[c]:>9}" for c in COLUMNS))
        for r in rows:
            out.append("  " + f"{r['stream'][:9]:<10}" + "".join(f"{r[c]:>9,}" for c in COLUMNS))
        more = led["streams_total"] - len(rows)
        if more > 0:
            out.append(f"  (+{more} more streams)")
    return out


def _nl_cell(r: dict) -> str:
    """One detector's linear-conversion nonlinearity: value +- sigma, a 3-sigma bound, or its status."""
    if r.get("resolved"):
        return f"{r['id']} {abs(r['nl_per_pw']):.3g}+-{r['sigma_per_pw']:.2g}"
    if r.get("bound_per_pw") is not None:
        return f"{r['id']} <{r['bound_per_pw']:.2g}"
    return f"{r['id']} {r['status'].replace('_', ' ')}"


def leakage_lines(leak: dict, max_listed: int = 12) -> list[str]:
    """The live leakage (``monitor/leakage_live.py``): the linear conversion's 2f -> 4f nonlinearity against
    MNTES per measured detector (pW^-1, requirement 0.014), its window and f_HWP; MNTES's own is not live."""
    if not leak or not leak.get("enabled"):
        return [f"linear conversion leakage: {leak.get('why', 'off')}"] if leak else []
    req = leak["requirement_per_pw"]
    if leak.get("t_ns") is None:
        return [f"linear conversion leakage (2f->4f vs MNTES, requirement {req:g} pW^-1): {leak.get('why', '')}"]
    med = leak["median"]
    if med["value_per_pw"] is not None:
        m = f"median {med['value_per_pw']:.3g}+-{med['sigma_per_pw']:.2g} pW^-1"
    elif med["bound_per_pw"] is not None:
        m = f"median < {med['bound_per_pw']:.2g} pW^-1 (3 sigma, {med['n_resolved']} of {med['n_measured']} resolved)"
    else:
        m = "no detector measured"
    f = "-" if leak["f_hwp_hz"] is None else f"{leak['f_hwp_hz']:.5g} Hz"
    rows = leak["detectors"]
    fitted = max((r.get("window_s") or 0.0 for r in rows), default=0.0)
    out = [f"linear conversion leakage (2f->4f vs MNTES, requirement {req:g} pW^-1): {m}; f_HWP {f} "
           f"({leak['f_hwp_source']}), window {fitted:.1f} s fitted of {leak['window_s']:g} s, every "
           f"{leak['every_s']:g} s"]
    more = f" (+{len(rows) - max_listed} more)" if len(rows) > max_listed else ""
    out.append("  " + ", ".join(_nl_cell(r) for r in rows[:max_listed]) + more)
    if leak.get("shadow"):
        out.append(f"  shadow: {leak['shadow']}; MNTES residual: {leak['mntes']}")
    return out

"""The chaos run of issue 22: router, source, converter and recorder as processes; every one stalled (SIGSTOP) and
killed (SIGKILL, then restarted) at seeded moments, and a CPU hog; afterwards the ledger and the recording.

``mntes-stream bench chaos`` is the same run (``mntes_stream/bench/chaos.py``); here it runs once, in about
two minutes, and every check of it must hold.
"""

from __future__ import annotations

import pytest

from mntes_stream.bench.chaos import EVENTS, run_chaos

pytestmark = pytest.mark.slow


def test_every_stall_and_kill_leaves_a_balanced_ledger_and_a_complete_recording(tmp_path):
    res = run_chaos(tmp_path, duration_s=75.0, seed=1, modules=4, channels=16, events=EVENTS)
    assert [e["event"] for e in res["events"]] and len(res["events"]) == len(EVENTS)
    assert all(rc == 0 for rc in res["return_codes"].values()), res["return_codes"]
    # The last converter's ledger balances per stream, and its final line says the lost it holds.
    assert res["checks"]["converter_ledger_balances"] and res["checks"]["converter_line_says_lost"], res
    # Counts are recorded whatever was stalled or killed (zenoh history and recovery), the source's own downtime
    # excepted; offline convert gives power for every one of them.
    assert res["checks"]["recording_counts_complete"], res["recording_gaps"]
    assert res["checks"]["offline_converts_every_recorded_chunk"], res["offline_ledger_line"]
    # No summary hides a chunk: counts recorded without power are at most what the converters reported lost.
    assert res["checks"]["no_summary_hides_a_chunk"], (res["recorded_counts_without_power"],
                                                       res["converter_lost_reported_all_runs"],
                                                       res["without_power_seq_t_s"], res["events"], res["warnings"])
    # The ledger over every converter run (each chunk once, as `up` says it) loses no more than that bound.
    assert res["converter_ledger_line_all_runs"].startswith("received ")
    assert res["converter_lost_all_runs"] <= res["converter_lost_reported_all_runs"], res["converter_ledger_line_all_runs"]
    assert res["ok"] and res["recorded_counts_chunks"] > 1000

"""A lab's network (issue 33): DAQ host, analysis host and laptop as network namespaces this test makes itself,
joined by veth links to a bridge; netem delay and loss on every link, a 15 s partition of the DAQ link, a router
restart. Every ledger accounts for every chunk the source published, what the partition lost beyond the
source's history is said in every summary, and the services reconnect by themselves.

``mntes-stream bench chaos-net`` is the same run (``mntes_stream/bench/chaos_net.py``). Needs root for
``ip netns`` (CI has it); skipped with the reason elsewhere. Every namespace is deleted at the end, on failure too.
"""

from __future__ import annotations

import os
import subprocess
import warnings

import pytest

from mntes_stream.bench.chaos_net import Lab, run_chaos_net, skip_reason

pytestmark = pytest.mark.slow

_REASON = skip_reason()
needs_netns = pytest.mark.skipif(bool(_REASON), reason=_REASON or "ip netns available")


def _namespaces() -> set[str]:
    return set(subprocess.run(["ip", "netns", "list"], capture_output=True, text=True).stdout.split())


@needs_netns
def test_a_partition_longer_than_the_history_is_stated_in_every_summary(tmp_path):
    before = _namespaces()
    res = run_chaos_net(tmp_path, partition_s=15.0, history_s=10.0, modules=1, channels=8)
    if not res["impairment"].startswith("netem"):
        warnings.warn(f"chaos-net ran without tc netem: {res['impairment']}", stacklevel=1)
    # Nothing left behind: every namespace of the run is gone.
    assert not {n for n in _namespaces() - before if n.startswith(f"mntes-{os.getpid()}-")}
    c = res["checks"]
    assert c["every_process_ended_cleanly"], res["return_codes"]
    assert c["source_summary_counts_published"], res["counts_published"]
    # A published chunk that appears in no ledger fails here: received - duplicate + never received = published.
    assert c["converter_accounts_for_every_published_chunk"], res["accounts"]["converter"]
    assert c["recorder_accounts_for_every_published_chunk"], res["accounts"]["recorder"]
    # The partition (15 s) outlasted the history (10 s): both ledgers lost chunks, and their closing lines say so.
    assert all(n > 0 for n in res["never_received"].values()), res["never_received"]
    assert c["lost_only_beyond_history"], (res["never_received"], res["expected_lost_chunks_per_stream_about"])
    assert c["closing_lines_say_lost"], (res["converter_ledger_line"], res["recorder_ledger_line"])
    assert c["recording_matches_recorder_ledger"], (res["recorded_counts_chunks"], res["recorder_ledger_line"])
    # Nobody was restarted by hand: after the link came back and after the router restart, counts were recorded.
    assert c["services_reconnected"], (res["reconnect_after_link_up_s"], res["reconnect_after_router_restart_s"])
    assert c["monitor_saw_the_ledger"], (res["monitor_last_ledger_line"], res["monitor_traceback"])
    assert res["ok"]


@needs_netns
def test_the_lab_deletes_its_namespaces_even_when_building_fails():
    before = _namespaces()

    class BadLab(Lab):
        HOSTS = ("daq", "a-host-name-longer-than-an-interface-may-be")  # `ip link add` refuses it: a real failure

    with pytest.raises(subprocess.CalledProcessError):
        BadLab(0.0, 0.0)
    assert not {n for n in _namespaces() - before if n.startswith(f"mntes-{os.getpid()}-")}

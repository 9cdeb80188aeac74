"""Two sources on one setup publish the same counts keys: a conflict, said by every summary, and nothing called lost.

Measured before (issue 33): two publishers on the same counts keys (two bridges on one setup, a misconfigured
lab): every chunk was converted, yet the converter's and the recorder's summaries both ended ``lost 3192``, and
nothing said there were two publishers. Here, a real run on loopback (a router, every service a client): two
minimal sources started a second apart (so their chunk numbers differ by about ten), a converter and a recorder
writing MCAP. Each publisher is told apart by zenoh's source info (the id of the session that published).
"""

from __future__ import annotations

import json
import re
import time

import pytest
from test_unpowered_hole import _Layout, _mntes, _seqs, _wait_seq

from mntes_stream.io.mcap import Session
from mntes_stream.io.messages import StatusMessage

pytestmark = pytest.mark.slow


def test_two_sources_on_one_key_are_a_conflict_and_nothing_is_called_lost(tmp_path):
    run = _Layout(tmp_path)
    try:
        conv = run.converter()
        first = run.source()
        _wait_seq(run.sub, "counts", 10, 90)  # the first source 1 s in: the second one's numbers differ
        second = run.start(f"mntes-stream serve --config services/source.toml {run.c} --set zenoh.history_s=1")
        conv.wait_for(r"conflict: 2 publishers send mntes/lab/counts/0/\d side by side", 60)
        time.sleep(2.0)  # both publish side by side
        beats = {b["service"]: b for b in json.loads(run.ps("--json").stdout)["services"]}
        ps_text = run.ps().stdout
        assert second.interrupt() in (0, 130)
        run.src = first
        run.stop()
    finally:
        run.close()
    for p in (run.rec, conv, first, second):
        assert not any("Traceback" in line for line in p.seen), "".join(p.seen)
    counts = _seqs(tmp_path / "rec", "counts")  # numbers as recorded: both sources' (they overlap)
    n_counts = sum(1 for m in Session(tmp_path / "rec").iter_messages() if "/counts/" in m.topic)
    assert sorted(counts) == ["0/0", "0/1"] and n_counts > 2 * max(len(s) for s in counts.values()) - 40

    # The converter: every chunk of both converted, none lost, and the conflict said (log, status, ps).
    last = [line for line in conv.seen if line.startswith("converter converter: ")][-1]
    m = re.match(r"converter converter: received (\d+) chunks: converted (\d+); lost 0 of (\d+)$", last.strip())
    assert m and m.group(1) == m.group(2) == m.group(3), last
    assert int(m.group(1)) >= n_counts - 4, (last, n_counts)  # (a source's last chunks may not reach a stopping one)
    statuses = [StatusMessage.from_bytes(m.payload) for m in Session(tmp_path / "rec").iter_messages()
                if m.topic == "mntes/lab/status/converter"]
    assert statuses[-1].conflicts == {"0/0": 2, "0/1": 2} and statuses[-1].chunks_lost == 0
    assert beats["converter"]["conflicts"] == {"0/0": 2, "0/1": 2}, beats["converter"]
    assert beats["recorder"]["conflicts"] == {"0/0": 2, "0/1": 2}, beats["recorder"]
    rows = [line for line in ps_text.splitlines() if line.startswith(("converter ", "recorder "))]
    assert len(rows) == 2 and all("CONFLICT publishers 0/0:2,0/1:2" in r for r in rows), ps_text

    # The recorder: every chunk recorded, none lost, and the conflict in its closing line and in inspect.
    last = [line for line in run.rec.seen if line.startswith("recorder: ")][-1]
    assert last.startswith(f"recorder: received {n_counts} chunks: recorded {n_counts}; lost 0 of {n_counts}"), last
    assert ("; WARNING 2 counts stream(s) sent by more than one publisher side by side (0/0 by 2, 0/1 by 2): two "
            "sources or bridges on one setup?") in last, last
    res = _mntes("inspect", "rec", cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    assert f"recorder: counts received {n_counts} chunks: recorded {n_counts}; lost 0 of {n_counts}" in res.stdout
    assert "  CONFLICT: 2 counts stream(s) sent by more than one publisher side by side (0/0 by 2" in res.stdout

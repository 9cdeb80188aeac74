"""services/README.md's secured deployment, run command for command on loopback (bounded).

The router logs every session in (zenoh user/password) and gives each user only
what its service needs (zenoh access control). Checked here with the real
services and real zenoh sessions: a session without a login, or with a wrong
password, is refused; a stranger in peer mode that reaches the router's port
receives nothing and nothing it publishes reaches the converter; a logged-in
reader that publishes counts is dropped at the router; the same forged counts
sent with the source's login do reach the converter (so the checks can fail);
the credentialed services convert, record and are listed by ``ps``.
"""

from __future__ import annotations

import json
import re
import shlex
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from test_services_walkthrough import Proc

from mntes_stream.core.timing import DFMUX_SAMPLE_RATE_HZ
from mntes_stream.errors import TransportError
from mntes_stream.io import keys
from mntes_stream.io.messages import CountsChunk, PowerChunk, StatusMessage, decode
from mntes_stream.io.transport import Publishers, QueueSubscriber, ZenohSettings, free_tcp_port, open_session

ROOT = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.slow


def _commands() -> list[str]:
    text = (ROOT / "services" / "README.md").read_text()
    section = text.split("## A secured deployment", 1)[1].split("\n## ", 1)[0]
    (block,) = re.findall(r"```\n(.*?)```", section, re.S)
    return [ln for ln in block.splitlines() if ln.strip()]


def _login(tmp_path: Path, user: str) -> ZenohSettings:
    return ZenohSettings(config_file=str(tmp_path / "services" / "secure" / f"zenoh-{user}.json5"))


def _forged(seq: int) -> bytes:
    """A valid counts chunk for a module the converter knows (b0m0, 16 channels of services/params.toml)."""
    n = 15
    counts = np.full((16, n), 1000, dtype=np.int32)
    return CountsChunk("lab", 0, 0, np.arange(16, dtype=np.int32), seq, time.time_ns(), DFMUX_SAMPLE_RATE_HZ,
                       counts, counts, time.time_ns()).to_bytes()


def _statuses(sub, timeout_s: float) -> list[StatusMessage]:
    out = []
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        item = sub.get(timeout_s=0.1)
        if item is not None and "/status/" in item[0]:
            out.append(decode(item[1]))
    return out


def _wait_status(sub, pred, timeout_s: float) -> StatusMessage:
    deadline = time.monotonic() + timeout_s
    seen = None
    while time.monotonic() < deadline:
        item = sub.get(timeout_s=0.1)
        if item is not None and "/status/" in item[0]:
            seen = decode(item[1])
            if pred(seen):
                return seen
    raise AssertionError(f"no such status within {timeout_s} s; last {seen}")


def test_secured_recipe_refuses_strangers_and_serves_its_users(tmp_path):
    router_cmd, conv_cmd, rec_cmd, src_cmd, mon_cmd, ps_cmd = _commands()
    port = free_tcp_port()
    shutil.copytree(ROOT / "services", tmp_path / "services", ignore=shutil.ignore_patterns("recordings", "*-params.toml"))
    for f in (tmp_path / "services" / "secure").glob("*.json5"):
        f.write_text(f.read_text().replace("7447", str(port)))
    endpoint = f"tcp/127.0.0.1:{port}"
    procs: list[Proc] = []
    try:
        procs.append(router := Proc(router_cmd, tmp_path))
        router.wait_for(r"router router: zenoh id")
        procs.append(conv := Proc(conv_cmd, tmp_path))
        conv.wait_for(r"converter converter: \d+ detectors")

        # No login, or a wrong password: the session is refused while it is set up.
        with pytest.raises(TransportError, match="cannot open zenoh session"):
            open_session(ZenohSettings(mode="client", connect=(endpoint,)))
        wrong = json.dumps({"user": "monitor", "password": "guess"})
        with pytest.raises(TransportError, match="cannot open zenoh session"):
            open_session(ZenohSettings(mode="client", connect=(endpoint,), cfg=(f"transport/auth/usrpwd:{wrong}",)))

        with open_session(_login(tmp_path, "operator")) as operator, \
                open_session(ZenohSettings(mode="peer", connect=(endpoint,))) as stranger, \
                open_session(_login(tmp_path, "monitor")) as reader, \
                open_session(_login(tmp_path, "source")) as source:
            watch = QueueSubscriber(operator, ["mntes/lab/status/**", "mntes/lab/power/**"])
            spy = QueueSubscriber(stranger, ["mntes/**"])
            time.sleep(1.0)  # subscriptions reach the router
            strangers, readers = Publishers(stranger), Publishers(reader)
            for i in range(20):  # forged counts from a stranger (peer mode) and from a logged-in reader
                strangers.put(keys.counts_key("lab", 0, 0), _forged(1000 + i))
                readers.put(keys.counts_key("lab", 0, 0), _forged(2000 + i))
                time.sleep(0.05)
            # Two statuses after the last forgery (1 s cadence): the converter received none of them.
            after = _statuses(watch, 2.5)
            assert len(after) >= 2 and all(s.chunks_received == 0 and not s.bad_messages for s in after), after
            # The same chunks with the source's login get through: the checks above can fail.
            sources = Publishers(source)
            for i in range(5):
                sources.put(keys.counts_key("lab", 0, 0), _forged(3000 + i))
            _wait_status(watch, lambda s: s.chunks_received == 5, 10)
            strangers.close(), readers.close(), sources.close()

            # The recipe's services: the operator reads power from both modules, the stranger nothing at all.
            procs.append(rec := Proc(rec_cmd, tmp_path))
            rec.wait_for(r"recording mntes/lab/\*\* into")
            procs.append(src := Proc(src_cmd, tmp_path))
            modules = set()
            deadline = time.monotonic() + 60
            while modules != {0, 1}:
                assert time.monotonic() < deadline, modules
                item = watch.get(timeout_s=0.2)
                if item is not None and "/power/" in item[0]:
                    pw = decode(item[1])
                    assert isinstance(pw, PowerChunk)
                    if np.isfinite(pw.p_opt_w).all():
                        modules.add(pw.module)
            procs.append(mon := Proc(mon_cmd, tmp_path))
            mon.wait_for(r"housekeeping: t_bath \d+\.\d+ mK", 90)
            res = subprocess.run([sys.executable, "-m", "mntes_stream", *shlex.split(ps_cmd)[1:]], cwd=tmp_path,
                                 capture_output=True, text=True, timeout=60)
            assert res.returncode == 0 and "Traceback" not in res.stderr, res.stderr
            for service in ("router", "converter", "recorder", "source", "monitor"):
                assert re.search(rf"^{service}\s", res.stdout, re.M), res.stdout
            # Not one message from any service reached the stranger: only its own (local delivery).
            spied = list(spy.drain())
            assert all(k == keys.counts_key("lab", 0, 0) and 1000 <= decode(p).seq < 1020 for k, p, _ in spied)
            assert not list(stranger.info.routers_zid()) and not list(stranger.info.peers_zid())
            watch.close()
            spy.close()
        for p in (mon, src, rec, conv):
            assert p.interrupt() in (0, 130)
            assert not any("Traceback" in line for line in p.seen), "".join(p.seen)
        res = subprocess.run([sys.executable, "-m", "mntes_stream", "inspect", "services/recordings/"], cwd=tmp_path,
                             capture_output=True, text=True, timeout=120)
        assert res.returncode == 0, res.stderr
        counts = {m.group(2): int(m.group(1)) for m in re.finditer(r"^\s+(\d+)\s+(\S+)$", res.stdout, re.M)}
        assert sum(n for t, n in counts.items() if "/power/" in t) > 0
        assert sum(n for t, n in counts.items() if "/counts/" in t) > 0
    finally:
        for p in procs:
            if p.p.poll() is None:
                p.interrupt(30)

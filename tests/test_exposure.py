"""Nothing binds every interface unless ``listen`` is given explicitly, in every zenoh mode.

The sockets checked are the ones the process really holds (``psutil``), not the config: a
zenoh default that listens on ``tcp/[::]:0`` (peer) or ``tcp/[::]:7447`` (router) shows up here.
"""

from __future__ import annotations

import json
import socket
import time

import psutil
import pytest

from mntes_stream.io.transport import ROUTER_PORT, ZenohSettings, describe_config, loopback, open_session, zenoh_config


def _bound() -> set[tuple[str, int, str]]:
    """(ip, port, kind) of every TCP listening socket and every bound UDP socket of this process."""
    out = set()
    for c in psutil.Process().net_connections(kind="inet"):
        if c.type == socket.SOCK_STREAM and c.status == psutil.CONN_LISTEN:
            out.add((c.laddr.ip, c.laddr.port, "tcp"))
        elif c.type == socket.SOCK_DGRAM and c.laddr:
            out.add((c.laddr.ip, c.laddr.port, "udp"))
    return out


def _opened(settings: ZenohSettings) -> set[tuple[str, int, str]]:
    """The sockets a session with ``settings`` adds to this process while it is open."""
    before = _bound()
    with open_session(settings):
        deadline = time.monotonic() + 2.0
        new = _bound() - before
        while not new and time.monotonic() < deadline:  # listeners come up asynchronously
            time.sleep(0.05)
            new = _bound() - before
        time.sleep(0.2)
        return _bound() - before


def _port_free(port: int) -> bool:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        try:
            s.bind(("0.0.0.0", port))
        except OSError:
            return False
    return True


@pytest.fixture
def peer():
    """A loopback peer for clients to connect to."""
    with open_session(loopback()) as session:
        time.sleep(0.2)
        ports = {p for ip, p, kind in _bound() if kind == "tcp" and ip == "127.0.0.1"}
        yield session, ports


def _file(tmp_path, doc: dict):
    path = tmp_path / f"{doc['mode']}.json5"
    path.write_text(json.dumps(doc))
    return str(path)


@pytest.mark.parametrize("how", ["config_file", "ZENOH_CONFIG"])
@pytest.mark.parametrize("mode", ["peer", "client", "router"])
def test_a_config_file_without_listen_binds_loopback_only(mode, how, tmp_path, monkeypatch, peer):
    _, peer_ports = peer
    doc = {"mode": mode, "transport": {"unicast": {"max_links": 1}}}  # a file that names other things
    if mode == "client":
        doc["connect"] = {"endpoints": [f"tcp/127.0.0.1:{p}" for p in sorted(peer_ports)]}
    path = _file(tmp_path, doc)
    if how == "ZENOH_CONFIG":
        monkeypatch.setenv("ZENOH_CONFIG", path)
        settings = ZenohSettings()
    else:
        settings = ZenohSettings(config_file=path)
    eff = describe_config(zenoh_config(settings))
    assert eff["mode"] == mode
    if mode == "router" and not _port_free(ROUTER_PORT):
        assert eff["listen/endpoints"] == [f"tcp/127.0.0.1:{ROUTER_PORT}"]
        pytest.skip(f"port {ROUTER_PORT} is in use here: the router's sockets cannot be opened (config checked)")
    new = _opened(settings)
    assert all(ip == "127.0.0.1" for ip, _, _ in new), new
    if mode == "client":
        assert not new  # a client only connects
    else:
        assert {kind for _, _, kind in new} == {"tcp"} and len(new) == 1, new
    if mode == "router":
        assert new == {("127.0.0.1", ROUTER_PORT, "tcp")}


@pytest.mark.parametrize("mode", ["peer", "router"])
def test_the_mode_flag_over_a_file_keeps_loopback(mode, tmp_path):
    path = _file(tmp_path, {"mode": "client"})
    settings = ZenohSettings(config_file=path, mode=mode)
    port = ROUTER_PORT if mode == "router" else 0
    assert describe_config(zenoh_config(settings))["listen/endpoints"] == [f"tcp/127.0.0.1:{port}"]
    if mode == "router" and not _port_free(ROUTER_PORT):
        pytest.skip(f"port {ROUTER_PORT} is in use here (config checked)")
    new = _opened(settings)
    assert new and all(ip == "127.0.0.1" for ip, _, _ in new), new


def test_other_listen_options_do_not_turn_the_default_off():
    # listen/timeout_ms names how to listen, not where: the loopback default stays.
    for cfg in (("listen/timeout_ms:1000",), ('listen:{timeout_ms: 1000}',)):
        new = _opened(ZenohSettings(cfg=cfg))
        assert new and all(ip == "127.0.0.1" for ip, _, _ in new), (cfg, new)


def test_listen_given_explicitly_is_honoured_even_on_every_interface():
    # The check above can fail: an explicit wildcard listen really binds every interface.
    for settings in (ZenohSettings(listen=("tcp/0.0.0.0:0",)), ZenohSettings(cfg=('listen/endpoints:["tcp/0.0.0.0:0"]',))):
        new = _opened(settings)
        assert {ip for ip, _, _ in new} == {"0.0.0.0"}, new


def test_no_udp_scouting_socket_by_default():
    new = _opened(ZenohSettings())
    assert not [s for s in new if s[2] == "udp"], new

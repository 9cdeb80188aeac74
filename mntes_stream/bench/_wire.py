"""A netem stand-in for kernels without ``sch_netem``: forwards Ethernet frames between two interfaces of one
namespace with a fixed delay and a random loss, each direction (``python -m mntes_stream.bench._wire A B
DELAY_MS LOSS_PCT SEED``; runs until killed).

The frames are real (AF_PACKET sockets on veth ends): TCP sees the delay, retransmits what is dropped, and a
port taken down (a partition) drops everything meanwhile. Frames go with their virtio-net header
(checksum and segmentation state as the sender left them); the senders' ``gso_max_size`` is kept at the MTU
(``chaos_net.Lab``) so that loss falls on single segments, as on a wire.
"""

from __future__ import annotations

import heapq
import random
import selectors
import socket
import sys
import time

_ETH_P_ALL = 0x0003
_PACKET_OUTGOING = 4  # a frame this host sent: not one to forward
_SOL_PACKET, _PACKET_VNET_HDR = 263, 15


def _open(ifname: str) -> socket.socket:
    s = socket.socket(socket.AF_PACKET, socket.SOCK_RAW, socket.htons(_ETH_P_ALL))
    # Each frame with its virtio-net header: a frame whose checksum the sender left to the "hardware" (veth's
    # offload) keeps that state when it is sent on, rather than arriving with a checksum never filled in.
    s.setsockopt(_SOL_PACKET, _PACKET_VNET_HDR, 1)
    s.bind((ifname, 0))
    s.setblocking(False)
    return s


def wire(a: str, b: str, delay_s: float, loss: float, seed: int) -> None:
    rng = random.Random(seed)
    socks = {a: _open(a), b: _open(b)}
    other = {socks[a]: socks[b], socks[b]: socks[a]}
    sel = selectors.DefaultSelector()
    for s in socks.values():
        sel.register(s, selectors.EVENT_READ)
    due: list[tuple[float, int, socket.socket, bytes]] = []
    n = 0
    while True:
        timeout = max(0.0, due[0][0] - time.monotonic()) if due else 1.0
        for key, _ in sel.select(timeout):
            s = key.fileobj
            while True:
                try:
                    frame, addr = s.recvfrom(65536)
                except BlockingIOError:
                    break
                except OSError:  # the port is down (a partition): nothing comes
                    break
                if addr[2] == _PACKET_OUTGOING or rng.random() < loss:
                    continue
                n += 1
                heapq.heappush(due, (time.monotonic() + delay_s, n, other[s], frame))
        now = time.monotonic()
        while due and due[0][0] <= now:
            _, _, out, frame = heapq.heappop(due)
            try:
                out.send(frame)
            except OSError:  # the port is down, or its queue full: the frame is lost, as on a wire
                pass


if __name__ == "__main__":
    a, b, delay_ms, loss_pct, seed = sys.argv[1:6]
    wire(a, b, float(delay_ms) / 1e3, float(loss_pct) / 100.0, int(seed))

"""How much a simulated USB-CAN adapter carries between two processes' worth of python-can.

Compares, in one run, the two ways issue 10 allowed for sharing a CAN bus across processes on a
kernel without CAN: the SLCAN adapter on a pty (crtk_bridge/sim/slcan.py, python-can ``slcan``)
and a socketcand server on loopback (a minimal one written here, only for this comparison;
python-can ``socketcand``). For each, with python-can's own client:

- frames/s master -> bus and bus -> master (a burst of N frames, time until the last arrives),
- SYNC -> TPDO round trip (p50 / p99) with a simulated CiA 402 drive answering on SYNC.

Usage: python bench/bench_can_adapter.py [--frames 3000] [--syncs 300]
Figures are printed, never asserted (the host is shared and noisy).
"""

from __future__ import annotations

import argparse
import logging
import socket
import sys
import threading
import time
from pathlib import Path

import can
import canopen

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # run from a clone without installing, as the other benches

from crtk_bridge.sim.canbus import LocalBus  # noqa: E402
from crtk_bridge.sim.canopen402 import CanopenSimulator, make_object_dictionary


class MiniSocketcand:
    """Just enough of socketcand's raw mode for python-can's client, bridged to a virtual bus."""

    def __init__(self, channel: str):
        self.bus = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)
        self.srv = socket.socket()
        self.srv.bind(("127.0.0.1", 0))
        self.srv.listen(1)
        self.port = self.srv.getsockname()[1]
        self.conn: socket.socket | None = None
        self.stop = threading.Event()
        threading.Thread(target=self._serve, daemon=True).start()

    def _serve(self) -> None:
        conn, _ = self.srv.accept()
        conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        conn.sendall(b"< hi >")
        conn.recv(256)  # < open ch >
        conn.sendall(b"< ok >")
        conn.recv(256)  # < rawmode >
        conn.sendall(b"< ok >")
        self.conn = conn
        threading.Thread(target=self._to_client, daemon=True).start()
        buf = b""
        while not self.stop.is_set():
            data = conn.recv(65536)
            if not data:
                return
            buf += data
            while b">" in buf:
                end = buf.index(b">")
                parts = buf[buf.index(b"<") + 1:end].split()
                buf = buf[end + 1:]
                if parts and parts[0] == b"send":
                    self.bus.send(can.Message(arbitration_id=int(parts[1], 16),
                                              data=bytes(int(x, 16) for x in parts[3:])))

    def _to_client(self) -> None:
        while not self.stop.is_set():
            msg = self.bus.recv(0.05)
            if msg is not None:
                t = time.time()
                self.conn.sendall(f"< frame {msg.arbitration_id:03X} {int(t)}.{int(t % 1 * 1e6):06d} "
                                  f"{msg.data.hex().upper()} >".encode())

    def close(self) -> None:
        self.stop.set()
        for s in (self.conn, self.srv):
            if s is not None:
                s.close()
        self.bus.shutdown()


WINDOW = 32  # frames in flight: a real bus and adapter buffer little, and drop the rest


def _throughput(client: can.BusABC, peer: can.BusABC, n: int) -> tuple[float, float]:
    """Sustained (frames/s client -> peer, frames/s peer -> client), at most WINDOW in flight."""
    out = []
    for sender, receiver in ((client, peer), (peer, client)):
        got = [0]
        done = threading.Event()

        def count():
            while got[0] < n:
                if receiver.recv(2.0) is None:
                    break
                got[0] += 1
            done.set()

        threading.Thread(target=count, daemon=True).start()
        t0 = time.perf_counter()
        for i in range(n):
            while i - got[0] >= WINDOW and not done.is_set():
                time.sleep(0.0002)
            sender.send(can.Message(arbitration_id=0x7E0, data=i.to_bytes(4, "little") * 2))
        done.wait(60)
        out.append(got[0] / (time.perf_counter() - t0))
    return out[0], out[1]


def _sync_rtt(client: can.BusABC, syncs: int) -> tuple[float, float]:
    """SYNC -> TPDO1 (statusword + position) of node 1, p50 / p99 in ms."""
    net = canopen.Network(client)
    net.NOTIFIER_CYCLE = 0.02
    net.connect()
    node = canopen.RemoteNode(1, make_object_dictionary(1))
    net.add_node(node)
    node.tpdo.read()
    node.tpdo[1].clear()
    node.tpdo[1].add_variable(0x6041)
    node.tpdo[1].add_variable(0x6064)
    node.tpdo[1].trans_type = 1
    node.tpdo[1].enabled = True
    node.tpdo.save()
    node.nmt.state = "OPERATIONAL"
    got = threading.Event()
    node.tpdo[1].add_callback(lambda _m: got.set())
    rtts = []
    for _ in range(syncs):
        got.clear()
        t0 = time.perf_counter()
        net.sync.transmit()
        if got.wait(0.5):
            rtts.append(time.perf_counter() - t0)
        time.sleep(0.002)
    net.notifier.stop(1.0)
    rtts.sort()
    return rtts[len(rtts) // 2] * 1e3, rtts[min(len(rtts) - 1, int(0.99 * len(rtts)))] * 1e3


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=3000)
    ap.add_argument("--syncs", type=int, default=300)
    args = ap.parse_args()
    logging.getLogger("can").setLevel(logging.ERROR)  # socketcand's client warns on split reads
    rows = []
    for name in ("slcan", "socketcand"):
        if name == "slcan":
            sim = CanopenSimulator([1], interface="slcan")
            sim.start()
            peer = LocalBus(sim._bus[1], receive_own_messages=False)  # the adapter's in-process bus
            make = lambda: can.Bus(interface="slcan", channel=sim.port, bitrate=1_000_000,  # noqa: E731
                                   sleep_after_open=0)
            server = None
        else:
            sim = CanopenSimulator([1], interface="virtual")
            sim.start()
            server = MiniSocketcand(sim.port)
            peer = can.Bus(interface="virtual", channel=sim.port, receive_own_messages=False)
            make = lambda: can.Bus(interface="socketcand", channel="can0", host="127.0.0.1",  # noqa: E731
                                   port=server.port, tcp_tune=True)
        client = make()
        try:
            rtt = _sync_rtt(client, args.syncs)
            tx, rx = _throughput(client, peer, args.frames)
            rows.append((name, tx, rx, *rtt))
        finally:
            client.shutdown()
            peer.shutdown()
            if server is not None:
                server.close()
            sim.stop()
    print(f"{'adapter':<11} {'master->bus f/s':>16} {'bus->master f/s':>16} {'SYNC->TPDO p50 ms':>18} {'p99 ms':>8}")
    for name, tx, rx, p50, p99 in rows:
        print(f"{name:<11} {tx:16.0f} {rx:16.0f} {p50:18.3f} {p99:8.3f}")
    (_, tx0, rx0, p0, _), (_, tx1, rx1, p1, _) = rows
    print(f"ratio slcan/socketcand: master->bus {tx0 / tx1:.2f}, bus->master {rx0 / rx1:.2f}, "
          f"SYNC->TPDO p50 {p0 / p1:.2f}")
    print("a 2-drive CSP cycle at 250 Hz needs ~1750 frames/s on the bus (1 SYNC + 2 RPDO + 4 TPDO)")


if __name__ == "__main__":
    main()

"""Round-trip latency and one-way throughput of the socmon transport on loopback.

Starts a pong process (this script with ``--pong``), then from this process:

0. baseline: raw 16-byte ping/pong answered inside the zenoh callbacks
   (no inbox, no thread hop: the floor of zenoh + its Python binding);
1. ping/pong round trips with a raw 16-byte payload (echoed as is);
2. ping/pong round trips with a codec message holding a 14-float64 array
   (encoded here, decoded + validated + re-encoded by the pong, decoded here);
3. a one-way flood of codec messages (``block`` congestion control), rate
   measured at the receiver.

Cases 1-3 go through :class:`broker_free_net.peer.Peer` (zenoh peer mode,
callback -> bounded inbox -> owning thread), i.e. the path socmon uses.

Usage::

    PYTHONPATH=. python scripts/bench_transport.py [--n 2000] [--warmup 200] [--flood 20000]
"""

from __future__ import annotations

import argparse
import os
import signal
import socket
import statistics
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from agent.protocol import topics  # noqa: E402
from broker_free_net.codec import F64Array, Int, Schema, decode, encode  # noqa: E402
from broker_free_net.config import NetConfig  # noqa: E402

MSG = Schema({"seq": Int(0), "x": F64Array((14,))})
RAW_PAYLOAD = b"0123456789abcdef"


def bench_keys(run: str) -> dict:
    return {
        "raw_ping": topics.ctl_key(run, 1), "raw_pong": topics.status_key(run, 1),
        "msg_ping": topics.ctl_key(run, 2), "msg_pong": topics.status_key(run, 2),
        "cb_ping": topics.ctl_key(run, 4), "cb_pong": topics.status_key(run, 4),
        "flood": topics.est_key(run, 0), "flood_end": topics.ctl_key(run, 3), "flood_report": topics.status_key(run, 3),
    }


def run_pong(run: str, listen: str) -> int:
    """Echo pings until SIGTERM; count flood messages and report on request."""
    stop = []
    signal.signal(signal.SIGTERM, lambda *_: stop.append(True))
    k = bench_keys(run)
    with topics.open_peer(NetConfig(run=run, listen=(listen,)), "bench", "pong") as peer:
        raw_in = peer.subscribe(k["raw_ping"])
        msg_in = peer.subscribe(k["msg_ping"])
        flood_in = peer.subscribe(k["flood"], maxlen=1 << 20)
        end_in = peer.subscribe(k["flood_end"])
        for key in (k["raw_pong"], k["msg_pong"], k["flood_report"], k["cb_pong"]):
            peer.publisher(key, block=True)
        # Baseline: echo straight from the zenoh callback (Peer never does this).
        cb_pub = peer.publisher(k["cb_pong"])
        cb_sub = peer.session.declare_subscriber(k["cb_ping"], lambda sample: cb_pub.put(sample.payload))
        first = last = None
        count = 0

        def take_flood():
            nonlocal first, last, count
            items = flood_in.drain()
            for item in items:
                first = item.arrival if first is None else first
                last = item.arrival
            count += len(items)
            return bool(items)

        while not stop:
            busy = take_flood()
            item = raw_in.poll()
            if item is not None:
                peer.put(k["raw_pong"], item.payload)
                busy = True
            item = msg_in.poll()
            if item is not None:
                msg = decode(item.payload, MSG)
                peer.put(k["msg_pong"], encode(msg))
                busy = True
            end = end_in.poll()
            if end is not None:
                # The end marker travels on another key and may overtake the
                # tail of the flood: wait for the announced count (or 5 s of silence).
                sent = decode(end.payload, MSG)["seq"]
                quiet_since = time.monotonic()
                while count < sent and time.monotonic() - quiet_since < 5.0:
                    if take_flood():
                        quiet_since = time.monotonic()
                    else:
                        peer.wait(timeout=0.05)
                span = (last - first) if count > 1 else 0.0
                peer.put(k["flood_report"], encode({"seq": count, "x": np.r_[span, np.zeros(13)]}))
                first = last = None
                count = 0
                busy = True
            if not busy:
                peer.wait(timeout=0.5)
        cb_sub.undeclare()
    return 0


def _round_trips(peer, inbox, ping_key, make_payload, check_reply, n, warmup, timeout=10.0):
    times = []
    for i in range(warmup + n):
        payload = make_payload(i)
        t0 = time.perf_counter()
        peer.put(ping_key, payload)
        item = inbox.get(timeout=timeout)
        t1 = time.perf_counter()
        if item is None:
            raise RuntimeError(f"no pong for round trip {i}")
        check_reply(i, item.payload)
        if i >= warmup:
            times.append(t1 - t0)
    return times


def _handshake(peer, inbox, key, payload, timeout=30.0):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        peer.put(key, payload)
        if inbox.get(timeout=0.2) is not None:
            time.sleep(0.2)
            inbox.drain()
            return
    raise RuntimeError("pong process did not answer")


def _percentile(values, q):
    return float(np.percentile(np.asarray(values), q))


def main(n: int = 2000, warmup: int = 200, flood: int = 20000) -> list[dict]:
    """Run the benchmark and print a table; return the rows."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    run = f"bench{os.getpid()}"
    listen = f"tcp/127.0.0.1:{port}"
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    pong = subprocess.Popen([sys.executable, str(Path(__file__).resolve()), "--pong", "--run", run, "--listen", listen],
                            env=env, start_new_session=True)
    k = bench_keys(run)
    rows = []
    try:
        with topics.open_peer(NetConfig(run=run, connect=(listen,)), "bench", "ping") as peer:
            raw_in = peer.subscribe(k["raw_pong"])
            msg_in = peer.subscribe(k["msg_pong"])
            report_in = peer.subscribe(k["flood_report"])
            for key in (k["raw_ping"], k["msg_ping"], k["flood"], k["flood_end"]):
                peer.publisher(key, block=True)
            _handshake(peer, raw_in, k["raw_ping"], RAW_PAYLOAD)
            x = np.random.default_rng(0).normal(size=14)
            _handshake(peer, msg_in, k["msg_ping"], encode({"seq": 0, "x": x}))

            def check_raw(i, payload):
                if payload != RAW_PAYLOAD:
                    raise RuntimeError("raw echo mismatch")

            times = _round_trips(peer, raw_in, k["raw_ping"], lambda i: RAW_PAYLOAD, check_raw, n, warmup)
            rows.append({"case": "raw bytes, Peer inboxes", "bytes": len(RAW_PAYLOAD), "n": n,
                         "median_us": 1e6 * statistics.median(times), "p99_us": 1e6 * _percentile(times, 99)})

            # Baseline: zenoh callbacks on both sides, no inbox/condition hop.
            got, event = [], threading.Event()

            def on_pong(sample):
                got.append(sample.payload.to_bytes())
                event.set()

            cb_sub = peer.session.declare_subscriber(k["cb_pong"], on_pong)
            cb_pub = peer.publisher(k["cb_ping"], block=True)
            deadline = time.monotonic() + 30.0
            while not got and time.monotonic() < deadline:
                cb_pub.put(RAW_PAYLOAD)
                event.wait(0.2)
            time.sleep(0.2)
            times = []
            for i in range(warmup + n):
                event.clear()
                got.clear()
                t0 = time.perf_counter()
                cb_pub.put(RAW_PAYLOAD)
                if not event.wait(10.0):
                    raise RuntimeError(f"no callback pong for round trip {i}")
                t1 = time.perf_counter()
                if i >= warmup:
                    times.append(t1 - t0)
            cb_sub.undeclare()
            rows.insert(0, {"case": "raw bytes, zenoh callbacks", "bytes": len(RAW_PAYLOAD), "n": n,
                         "median_us": 1e6 * statistics.median(times), "p99_us": 1e6 * _percentile(times, 99)})

            def check_msg(i, payload):
                if decode(payload, MSG)["seq"] != i:
                    raise RuntimeError("codec echo out of order")

            msg_len = len(encode({"seq": 1, "x": x}))
            times = _round_trips(peer, msg_in, k["msg_ping"], lambda i: encode({"seq": i, "x": x}),
                                 check_msg, n, warmup)
            rows.append({"case": "codec 14 x f64, Peer inboxes", "bytes": msg_len, "n": n,
                         "median_us": 1e6 * statistics.median(times), "p99_us": 1e6 * _percentile(times, 99)})

            t0 = time.perf_counter()
            for i in range(flood):
                peer.put(k["flood"], encode({"seq": i, "x": x}))
            send_rate = flood / (time.perf_counter() - t0)
            peer.put(k["flood_end"], encode({"seq": flood, "x": np.zeros(14)}))
            item = report_in.get(timeout=60.0)
            if item is None:
                raise RuntimeError("no flood report")
            report = decode(item.payload, MSG)
            received, span = report["seq"], float(report["x"][0])
            rows.append({"case": "codec one-way flood", "bytes": msg_len, "n": flood,
                         "sent_per_s": send_rate, "received": received,
                         "recv_per_s": received / span if span > 0 else float("nan")})
    finally:
        pong.send_signal(signal.SIGTERM)
        try:
            pong.wait(timeout=10)
        except subprocess.TimeoutExpired:
            os.killpg(pong.pid, signal.SIGKILL)
            pong.wait()

    print(f"{'case':<28} {'bytes':>5} {'n':>6} {'median us':>10} {'p99 us':>10}")
    for r in rows:
        if "median_us" in r:
            print(f"{r['case']:<28} {r['bytes']:>5} {r['n']:>6} {r['median_us']:>10.0f} {r['p99_us']:>10.0f}")
    for r in rows:
        if "recv_per_s" in r:
            print(f"{r['case']:<28} {r['bytes']:>5} {r['n']:>6}  sent {r['sent_per_s']:,.0f} msg/s, "
                  f"received {r['received']}/{r['n']} at {r['recv_per_s']:,.0f} msg/s")
    return rows


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--n", type=int, default=2000, help="measured round trips per case")
    parser.add_argument("--warmup", type=int, default=200, help="unmeasured round trips first")
    parser.add_argument("--flood", type=int, default=20000, help="messages in the one-way flood")
    parser.add_argument("--pong", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--run", help=argparse.SUPPRESS)
    parser.add_argument("--listen", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.pong:
        sys.exit(run_pong(args.run, args.listen))
    main(args.n, args.warmup, args.flood)

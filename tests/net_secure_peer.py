"""Secured peer used by the multi-process security tests (not a test module).

Run as ``python tests/net_secure_peer.py --keys DIR --identity agent-1 --run R
--listen tls/127.0.0.1:PORT [--connect EP] [--put KEY ...]`` with PYTHONPATH set to the
worktree root. It opens a :class:`~broker_free_net.peer.Peer` with the credentials of
IDENTITY, subscribes to ``socmon/<run>/**`` and watches liveliness, and prints one line per
event on stdout::

    ready
    got <key> <payload>        a sample it received
    alive <role> <id>          a liveliness token it sees appear

Every 50 ms it puts ``<n>`` on each ``--put`` key (n = 1, 2, ...), allowed or not, so that
tests can check what a receiving peer lets through from it.
"""

import argparse
import signal
import sys

from broker_free_net.config import NetConfig
from agent.protocol.topics import open_peer
from agent.protocol.topics import parse_identity


def main(keys_dir, identity, run, listen, connect, puts, peer_id=None) -> int:
    stop = []
    signal.signal(signal.SIGTERM, lambda *_: stop.append(True))
    role, i = parse_identity(identity)
    net = NetConfig(run=run, listen=tuple(listen) or None, connect=tuple(connect) or None,
                    keys=keys_dir, identity=identity)
    with open_peer(net, "inject" if role == "operator" else role, peer_id or i or 0) as peer:
        inbox = peer.subscribe(f"socmon/{run}/**", maxlen=1 << 16, include_local=False)
        watch = peer.watch_liveliness()
        for key in puts:
            peer.publisher(key, block=True)
        print("ready", flush=True)
        n = 0
        while not stop:
            n += 1
            for key in puts:
                peer.put(key, str(n).encode())
            peer.wait(timeout=0.05)
            for item in inbox.drain():
                print(f"got {item.key} {item.payload.decode(errors='replace')}", flush=True)
            for ev in watch.drain():
                if ev.alive:
                    print(f"alive {ev.role} {ev.id}", flush=True)
    return 0


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--keys", required=True)
    parser.add_argument("--identity", required=True)
    parser.add_argument("--run", required=True)
    parser.add_argument("--listen", action="append", default=[])
    parser.add_argument("--connect", action="append", default=[])
    parser.add_argument("--put", action="append", default=[])
    parser.add_argument("--peer-id", default=None)
    args = parser.parse_args()
    sys.exit(main(args.keys, args.identity, args.run, args.listen, args.connect, args.put, args.peer_id))

"""Tiny echo peer used by the multi-process transport tests (not a test module).

Run as ``python tests/net_echo_peer.py --run R --id 1 --listen tcp/127.0.0.1:PORT``
with PYTHONPATH set to the worktree root. It subscribes to
``socmon/<run>/ctl/<id>``, validates every payload with :data:`REQUEST`, and
answers each good one on ``socmon/<run>/status/<id>`` with the same ``seq`` and
``x`` plus its drop counters. Malformed payloads are only counted.
"""

import argparse
import signal
import sys

from agent.protocol import topics
from broker_free_net.codec import F64Array, Int, MessageStats, Schema, encode, try_decode
from broker_free_net.config import NetConfig

REQUEST = Schema({"seq": Int(0, 2**31), "x": F64Array((None,), required=False)})
REPLY = Schema({
    "seq": Int(0, 2**31),
    "x": F64Array((None,), required=False),
    "from": Int(0, 2**31),
    "accepted": Int(0),
    "dropped": Int(0),
})


def main(run: str, id: int, listen: list[str], connect: list[str]) -> int:
    stop = []
    signal.signal(signal.SIGTERM, lambda *_: stop.append(True))
    net = NetConfig(run=run, listen=tuple(listen), connect=tuple(connect))
    with topics.open_peer(net, "echo", id) as peer:
        inbox = peer.subscribe(topics.ctl_key(run, id))
        out_key = topics.status_key(run, id)
        peer.publisher(out_key, block=True)
        stats = MessageStats()
        print("ready", flush=True)
        while not stop:
            item = inbox.get(timeout=0.5)
            if item is None:
                continue
            msg = try_decode(item.payload, REQUEST, stats)
            if msg is None:
                continue
            reply = {"seq": msg["seq"], "from": id, "accepted": stats.accepted, "dropped": stats.total_dropped}
            if "x" in msg:
                reply["x"] = msg["x"]
            peer.put(out_key, encode(reply))
    return 0


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--run", required=True)
    parser.add_argument("--id", type=int, required=True)
    parser.add_argument("--listen", action="append", default=[])
    parser.add_argument("--connect", action="append", default=[])
    args = parser.parse_args()
    sys.exit(main(args.run, args.id, args.listen, args.connect))

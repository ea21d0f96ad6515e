"""``socmon inject``: change a link impairment of a running deployment.

Publishes one impairment change on ``socmon/<run>/impair`` and waits until the receiving
agent's status shows it (the client: :mod:`agent.run.inject`). Links are directed:
``SRC DST`` is the link on which agent DST receives agent SRC's estimates.

Examples::

    socmon inject delay 2 1 --steps 3 --run demo --connect tcp/127.0.0.1:7447
    socmon inject delay 2 1 --ms 30 --jitter 10 ...
    socmon inject drop 2 1 0.2 [--burst 5] ...
    socmon inject partition 2 1 on|off ...
    socmon inject clear 2 1 ...
    socmon inject clear-all ...
    socmon inject drop 2 1 0.2 --attach RUN_FOLDER     # a `socmon up` run, from its run.json
    socmon inject clear-all --run demo --connect ... --operator-key RUN_FOLDER/operator.key

``--operator-key`` was ``--control-key`` before: the old name still works and says on
stderr that it is deprecated (the monitor's ``--control-key`` is another key, the run's
control key).
"""

from __future__ import annotations

import sys

from agent.cli._common import (add_operator_key_arguments, int_flag, net_config_arg,
                               operator_signer, run_command)

HELP = "inject a link delay, drop rate or partition into a running deployment"


def add_arguments(parser) -> None:
    from broker_free_net.config import add_net_arguments

    sub = parser.add_subparsers(dest="what", metavar="WHAT", required=True)
    p = sub.add_parser("delay", help="delay on link SRC -> DST, in steps or in ms")
    _link(p)
    p.add_argument("--steps", type=int_flag(lo=0), default=None, help="delay in steps")
    p.add_argument("--ms", type=float, default=None, help="delay in milliseconds")
    p.add_argument("--jitter", type=float, default=None, help="extra uniform jitter in ms")
    p = sub.add_parser("drop", help="drop probability on link SRC -> DST")
    _link(p)
    p.add_argument("p", type=float, help="long-run fraction of messages dropped, in [0, 1]")
    p.add_argument("--burst", type=float, default=None,
                   help="mean burst length (>= 1) for bursty drops (default independent)")
    p = sub.add_parser("partition", help="cut (on) or restore (off) link SRC -> DST")
    _link(p)
    p.add_argument("state", choices=["on", "off"])
    p = sub.add_parser("clear", help="remove every impairment of link SRC -> DST")
    _link(p)
    p = sub.add_parser("clear-all", help="remove every impairment of every link")
    add_operator_key_arguments(p)
    for p in sub.choices.values():
        add_net_arguments(p)


def _link(p):
    p.add_argument("src", type=int_flag(lo=1), help="sending agent id")
    p.add_argument("dst", type=int_flag(lo=1), help="receiving agent id")
    add_operator_key_arguments(p)


def run(args) -> int:
    def body():
        from agent.run.inject import change_from_args, encode_change, inject

        change = change_from_args(args)
        signer = operator_signer(args, warn=lambda text: print(f"inject: warning: {text}",
                                                               file=sys.stderr))
        encode_change(change, signer, args.run)      # a bad value said before joining
        # signed afresh at each publication: the agents refuse a signed message seen
        # before (a replay), and a change is published until it is confirmed
        inject(net_config_arg(args, identity="operator"), change,
               lambda: encode_change(change, signer, args.run), args.timeout,
               confirm=not args.no_confirm,
               say=lambda text: print(f"inject: {text}", file=sys.stderr))
        return 0

    return run_command(body)

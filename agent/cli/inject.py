"""``socmon inject``: change a link impairment of a running deployment.

Publishes one impairment change on ``socmon/<run>/impair`` and waits until the receiving
agent's status shows it (the agents apply impairments on the receiving side). Links are
directed: ``SRC DST`` is the link on which agent DST receives agent SRC's estimates.

Examples::

    socmon inject delay 2 1 --steps 3 --run demo --connect tcp/127.0.0.1:7447
    socmon inject delay 2 1 --ms 30 --jitter 10 ...
    socmon inject drop 2 1 0.2 [--burst 5] ...
    socmon inject partition 2 1 on|off ...
    socmon inject clear 2 1 ...
    socmon inject clear-all ...
    socmon inject drop 2 1 0.2 --attach RUN_FOLDER     # a `socmon up` run, from its run.json
"""

from __future__ import annotations

from agent.cli._common import CommandError, int_flag, net_config_arg, run_command

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
    _common(p)
    for p in sub.choices.values():
        add_net_arguments(p)


def _common(p):
    from agent.cli._common import add_attach_argument

    add_attach_argument(p, takes=", and its operator key (RUN_FOLDER/operator.key) to sign "
                                 "the change")
    p.add_argument("--control-key", metavar="FILE",
                   help="the run's operator key (socmon up writes RUN_FOLDER/operator.key): "
                        "sign the change, as agents started with the run's manifest require")
    p.add_argument("--timeout", type=float, default=10.0,
                   help="seconds to wait for the agents to confirm (default 10)")
    p.add_argument("--no-confirm", action="store_true",
                   help="publish and exit without waiting for confirmation")


def _link(p):
    p.add_argument("src", type=int_flag(lo=1), help="sending agent id")
    p.add_argument("dst", type=int_flag(lo=1), help="receiving agent id")
    _common(p)


def change_from_args(args) -> tuple:
    """``(op, src, dst, params)`` of the change named by the arguments; CommandError if bad."""
    params = {}
    src = getattr(args, "src", None)
    dst = getattr(args, "dst", None)
    for name, v in (("SRC", src), ("DST", dst)):
        if v is not None and v < 1:
            raise CommandError(f"{name}: agent ids are >= 1, got {v}")
    if src is not None and src == dst:
        raise CommandError("SRC, DST: a link joins two different agents")
    if args.what == "delay":
        if args.steps is None and args.ms is None and args.jitter is None:
            raise CommandError("delay: give --steps, --ms and/or --jitter")
        if args.steps is not None:
            params["delay_steps"] = args.steps
        if args.ms is not None:
            params["delay_ms"] = args.ms
        if args.jitter is not None:
            params["jitter_ms"] = args.jitter
    elif args.what == "drop":
        params["drop"] = args.p
        if args.burst is not None:
            params["burst"] = args.burst
    elif args.what == "partition":
        params["partition"] = args.state == "on"
    op = {"delay": "set", "drop": "set", "partition": "set", "clear": "clear",
          "clear-all": "clear_all"}[args.what]
    return op, src, dst, params


def _confirmed(op, src, dst, params, statuses, alive) -> bool:
    if op == "clear_all":
        return bool(alive) and all(a in statuses and not statuses[a]["links"] for a in alive)
    st = statuses.get(dst)
    if st is None:
        return False
    links = st["links"]
    if op == "clear":
        return str(src) not in links
    got = links.get(str(src), {})
    defaults = {"delay_steps": 0, "delay_ms": 0.0, "jitter_ms": 0.0, "drop": 0.0,
                "burst": None, "partition": False}
    return all(got.get(k, defaults[k]) == v for k, v in params.items())


#: an agent absent this long while others are alive is reported at once, not at --timeout
ABSENT_S = 2.0


def _unused_link(op, src, dst, statuses) -> str | None:
    """Why a change on link ``src -> dst`` alters nothing now, or None: agent ``dst``'s
    current role does not listen to ``src`` (it applies once roles change).

    >>> _unused_link("set", 1, 2, {2: {"neighbours": {"3": 0.5}}})
    'agent 2 does not listen to agent 1 in its current role (it listens to 3): the change takes effect only if the roles change'
    >>> _unused_link("set", 3, 2, {2: {"neighbours": {"3": 0.5}}}) is None
    True
    """
    if op == "clear_all" or src is None or dst not in statuses:
        return None
    listens = sorted(int(j) for j in statuses[dst].get("neighbours", {}))
    if src in listens:
        return None
    what = f"it listens to {', '.join(map(str, listens))}" if listens else \
        "it has no role: a standby"
    return (f"agent {dst} does not listen to agent {src} in its current role ({what}): "
            "the change takes effect only if the roles change")


def run(args) -> int:

    def body():
        import os
        import sys
        import time

        from broker_free_net import keys
        from broker_free_net.codec import MalformedMessage, MessageStats, try_decode
        from broker_free_net.impair import encode_impairment
        from broker_free_net.peer import Peer

        from agent.protocol import wire

        from agent.cli._common import attach_run

        op, src, dst, params = change_from_args(args)
        info = attach_run(args)
        if args.control_key is None and info is not None and info.operator_key is not None:
            args.control_key = str(info.operator_key)
        sign = None
        if args.control_key:
            from agent.cli._common import load_signer

            signer = load_signer(args.control_key)
            if not args.run:
                raise CommandError("--control-key: give the run id too (--run)")
            sign = lambda m: signer.sign(m, args.run)      # noqa: E731
        try:
            payload = encode_impairment(op, src, dst, sign=sign, **params)
        except MalformedMessage as exc:
            raise CommandError(f"{args.what}: {exc}") from None
        net = net_config_arg(args, identity="operator")
        if not net.connect and not net.multicast:
            raise CommandError("--connect: give the endpoint of a process of the run "
                               "(or --multicast on a LAN)")
        stats = MessageStats()
        with Peer(net, "inject", f"p{os.getpid()}") as peer:
            status_in = peer.subscribe(keys.any_agent_pattern(net.run, "status"))
            watch = peer.watch_liveliness()
            key = keys.impair_key(net.run)
            peer.publisher(key, block=True)
            statuses = {}
            deadline = time.monotonic() + args.timeout
            absent_by = time.monotonic() + min(ABSENT_S, args.timeout)
            next_put = 0.0
            while True:
                alive = {int(i) for r, i in watch.alive() if r == "agent" and i.isdigit()}
                for item in status_in.drain():
                    m = try_decode(item.payload, wire.STATUS_SCHEMA, stats)
                    if m is not None:
                        statuses[m["agent"]] = m
                now = time.monotonic()
                # (re)publish until confirmed: a change is idempotent
                if now >= next_put and (dst is None or dst in alive):
                    peer.put(key, payload)
                    next_put = now + 0.5
                    if args.no_confirm:
                        print(f"inject: published {args.what} on {key}", file=sys.stderr)
                        return 0
                if next_put and _confirmed(op, src, dst, params, statuses, alive):
                    where = f"link {src} -> {dst}" if src is not None else "all links"
                    print(f"inject: {args.what} applied on {where}", file=sys.stderr)
                    unused = _unused_link(op, src, dst, statuses)
                    if unused:
                        print(f"inject: warning: {unused}", file=sys.stderr)
                    return 0
                if dst is not None and dst not in alive and alive and now > absent_by:
                    raise CommandError(
                        f"agent {dst} is not alive in run {net.run!r}; the agents alive are "
                        f"{', '.join(map(str, sorted(alive)))}", status=1)
                if now > deadline:
                    who = f"agent {dst}" if dst is not None else "the agents"
                    state = "not alive" if dst is not None and dst not in alive else \
                        "did not confirm"
                    raise CommandError(f"{who} {state} within {args.timeout:g} s "
                                       f"(run {net.run!r})", status=1)
                peer.wait(timeout=0.1)

    return run_command(body)

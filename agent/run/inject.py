"""Change a link impairment of a running run, and wait until the agents show it.

The change is published on ``socmon/<run>/impair``
(:func:`broker_free_net.impair.encode_impairment`, signed with the run's operator key when
the agents require it) and again every :data:`REPUBLISH_S` until it is confirmed (a
change is idempotent). The agents apply
impairments on the receiving side, so the change of the directed link ``SRC -> DST`` (the
link on which agent DST receives agent SRC's estimates) is confirmed by agent DST's
status; ``clear-all`` by the status of every agent alive.

The steps, in the order ``socmon inject`` takes them: :func:`change_from_args` names the
change, :func:`encode_change` encodes (and signs) it, :func:`inject` publishes it and waits.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass

from agent.run.inputs import InputError

__all__ = ["ABSENT_S", "REPUBLISH_S", "Change", "change_from_args", "operator_key_arg",
           "encode_change", "is_confirmed", "unused_link", "inject"]

#: an agent absent this long while others are alive is reported at once, not at the timeout
ABSENT_S = 2.0
#: seconds between two publications of a change not yet confirmed
REPUBLISH_S = 0.5
#: what an agent's status shows for a link parameter never set
_DEFAULTS = {"delay_steps": 0, "delay_ms": 0.0, "jitter_ms": 0.0, "drop": 0.0, "burst": None,
             "partition": False}


@dataclass(frozen=True)
class Change:
    """One impairment change: ``what`` the command's word (delay, drop, partition, clear,
    clear-all), ``op`` the wire's (set, clear, clear_all), the link ``src -> dst`` (None
    for clear_all) and the parameters set."""

    what: str
    op: str
    src: int | None
    dst: int | None
    params: dict

    @property
    def where(self) -> str:
        return f"link {self.src} -> {self.dst}" if self.src is not None else "all links"


def change_from_args(args) -> Change:
    """The :class:`Change` named by ``socmon inject``'s arguments; InputError if bad.

    >>> from types import SimpleNamespace as NS
    >>> change_from_args(NS(what="drop", src=2, dst=1, p=0.2, burst=None))
    Change(what='drop', op='set', src=2, dst=1, params={'drop': 0.2})
    >>> change_from_args(NS(what="delay", src=2, dst=1, steps=None, ms=None, jitter=None))
    Traceback (most recent call last):
    ...
    agent.run.inputs.InputError: delay: give --steps, --ms and/or --jitter
    """
    params = {}
    src = getattr(args, "src", None)
    dst = getattr(args, "dst", None)
    for name, v in (("SRC", src), ("DST", dst)):
        if v is not None and v < 1:
            raise InputError(f"{name}: agent ids are >= 1, got {v}")
    if src is not None and src == dst:
        raise InputError("SRC, DST: a link joins two different agents")
    if args.what == "delay":
        if args.steps is None and args.ms is None and args.jitter is None:
            raise InputError("delay: give --steps, --ms and/or --jitter")
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
    return Change(args.what, op, src, dst, params)


def operator_key_arg(operator_key, deprecated_control_key, warn=lambda text: None) -> tuple:
    """``(path, flag)`` of the operator key given to ``socmon inject`` (``(None, None)``:
    none given). ``--operator-key`` is its name; ``--control-key``, its name before, still
    works and ``warn(text)`` says it is deprecated (the monitor's ``--control-key`` is the
    run's control key, another key). Both given and different: InputError.

    >>> operator_key_arg("op.key", None)
    ('op.key', '--operator-key')
    >>> said = []
    >>> operator_key_arg(None, "op.key", warn=said.append)
    ('op.key', '--control-key')
    >>> said[0].split(" (")[0]
    '--control-key is deprecated for inject: use --operator-key'
    """
    if deprecated_control_key is None:
        return (operator_key, "--operator-key") if operator_key is not None else (None, None)
    if operator_key is not None and operator_key != deprecated_control_key:
        raise InputError(f"--control-key: the deprecated name of --operator-key, given with "
                         f"another file ({deprecated_control_key!r} and {operator_key!r}): "
                         "give --operator-key alone")
    warn("--control-key is deprecated for inject: use --operator-key (the same file, the "
         "run's operator key RUN_FOLDER/operator.key; monitor --control-key takes the "
         "control key, another one)")
    return deprecated_control_key, "--control-key"


def encode_change(change: Change, signer=None, run: str | None = None) -> bytes:
    """The payload of ``change``, signed by ``signer`` (a
    :class:`agent.protocol.control_auth.ControlSigner`) for run ``run`` when given;
    InputError naming what is wrong (a value out of range, a signer without a run)."""
    from broker_free_net.codec import MalformedMessage
    from broker_free_net.impair import encode_impairment

    sign = None
    if signer is not None:
        if not run:
            raise InputError("--operator-key: give the run id too (--run)")
        sign = lambda m: signer.sign(m, run)      # noqa: E731
    try:
        return encode_impairment(change.op, change.src, change.dst, sign=sign, **change.params)
    except MalformedMessage as exc:
        # "[range] field 'drop': 1.5 outside [0.0, 1.0]" -> "drop: 1.5 outside [0.0, 1.0]"
        detail = str(exc).split("] ", 1)[-1]
        if exc.field is not None:
            detail = detail.split(": ", 1)[-1]
        named = f"{exc.field} " if exc.field not in (None, change.what) else ""
        raise InputError(f"{change.what}: {named}{detail}") from None


def is_confirmed(change: Change, statuses: dict, alive) -> bool:
    """Whether the agents' ``statuses`` (agent id -> its last status) show ``change``;
    ``alive``: the ids of the agents alive.

    >>> c = Change("drop", "set", 2, 1, {"drop": 0.2})
    >>> is_confirmed(c, {1: {"links": {"2": {"drop": 0.2}}}}, {1, 2})
    True
    >>> is_confirmed(c, {1: {"links": {}}}, {1, 2})
    False
    """
    if change.op == "clear_all":
        return bool(alive) and all(a in statuses and not statuses[a]["links"] for a in alive)
    st = statuses.get(change.dst)
    if st is None:
        return False
    links = st["links"]
    if change.op == "clear":
        return str(change.src) not in links
    got = links.get(str(change.src), {})
    return all(got.get(k, _DEFAULTS[k]) == v for k, v in change.params.items())


def unused_link(change: Change, statuses: dict) -> str | None:
    """Why ``change`` on link ``src -> dst`` alters nothing now, or None: agent ``dst``'s
    current role does not listen to ``src`` (it applies once roles change).

    >>> unused_link(Change("drop", "set", 1, 2, {}), {2: {"neighbours": {"3": 0.5}}})
    'agent 2 does not listen to agent 1 in its current role (it listens to 3): the change takes effect only if the roles change'
    >>> unused_link(Change("drop", "set", 3, 2, {}), {2: {"neighbours": {"3": 0.5}}}) is None
    True
    """
    src, dst = change.src, change.dst
    if change.op == "clear_all" or src is None or dst not in statuses:
        return None
    listens = sorted(int(j) for j in statuses[dst].get("neighbours", {}))
    if src in listens:
        return None
    what = f"it listens to {', '.join(map(str, listens))}" if listens else \
        "it has no role: a standby"
    return (f"agent {dst} does not listen to agent {src} in its current role ({what}): "
            "the change takes effect only if the roles change")


def _rejected(status: dict) -> int:
    """The messages an agent's status says it refused for their signature (an impairment
    not signed with the run's operator key; not an assignment refused for its epoch)."""
    reasons = status.get("malformed_reasons")
    n = reasons.get("signature", 0) if isinstance(reasons, dict) else 0
    return n if isinstance(n, int) and not isinstance(n, bool) else 0


def inject(net, change: Change, payload: bytes, timeout: float, confirm: bool = True,
           say=print) -> None:
    """Publish ``payload`` (``change`` encoded, or a function that encodes and signs it
    afresh for each publication: a signed message sent again is a replay to the agents)
    to the run of ``net`` (a
    :class:`broker_free_net.config.NetConfig`) and, with ``confirm``, wait until the
    agents' statuses show it. ``say(text)`` is told what was done (and a warning when the
    receiving agent does not listen to the link now). InputError (status 1) when agent DST
    is not alive or nothing confirms within ``timeout`` seconds; (status 2) without an
    endpoint to connect to."""
    from agent.protocol import topics
    from broker_free_net.codec import MessageStats, try_decode

    from agent.protocol import wire

    if not net.connect and not net.multicast:
        raise InputError("--connect: give the endpoint of a process of the run "
                         "(or --multicast on a LAN)")
    dst = change.dst
    stats = MessageStats()
    with topics.open_peer(net, "inject", f"p{os.getpid()}") as peer:
        status_in = peer.subscribe(topics.any_agent_pattern(net.run, "status"))
        watch = peer.watch_liveliness()
        key = topics.impair_key(net.run)
        peer.publisher(key, block=True)
        statuses = {}
        rejected = {}              # agent -> control messages it had refused at the first put
        deadline = time.monotonic() + timeout
        absent_by = time.monotonic() + min(ABSENT_S, timeout)
        next_put = 0.0
        while True:
            alive = {int(i) for r, i in watch.alive() if r == "agent" and i.isdigit()}
            for item in status_in.drain():
                m = try_decode(item.payload, wire.STATUS_SCHEMA, stats)
                if m is not None:
                    statuses[m["agent"]] = m
                    if next_put:     # the signatures it refused since the first put
                        rejected.setdefault(m["agent"], _rejected(m))
            now = time.monotonic()
            refused = [a for a in ([dst] if dst is not None else sorted(statuses))
                       if a in rejected and _rejected(statuses[a]) > rejected[a]]
            if refused and not is_confirmed(change, statuses, alive):
                # with the agent's reason: its last refused control message's
                ctl = statuses[refused[0]].get("ctl")
                why = str(ctl.get("last_error") or "?")[:200] if isinstance(ctl, dict) else "?"
                raise InputError(
                    f"agent {refused[0]} refused the change ({why}): sign it with the run's "
                    "operator key (--operator-key RUN_FOLDER/operator.key, or --attach "
                    "RUN_FOLDER)", status=1)
            # (re)publish until confirmed: a change is idempotent
            if now >= next_put and (dst is None or dst in alive):
                peer.put(key, payload() if callable(payload) else payload)
                next_put = now + REPUBLISH_S
                if not confirm:
                    say(f"published {change.what} on {key}")
                    return
            if next_put and is_confirmed(change, statuses, alive):
                say(f"{change.what} applied on {change.where}")
                unused = unused_link(change, statuses)
                if unused:
                    say(f"warning: {unused}")
                return
            if dst is not None and dst not in alive and alive and now > absent_by:
                raise InputError(
                    f"agent {dst} is not alive in run {net.run!r}; the agents alive are "
                    f"{', '.join(map(str, sorted(alive)))}", status=1)
            if now > deadline:
                if not alive:
                    # no agent's token came at all: the run is not reached, which is not
                    # the same as its agent being dead
                    raise InputError(
                        f"no agent of run {net.run!r} seen within {timeout:g} s through "
                        f"{', '.join(net.connect or ()) or 'multicast'}: is the run up, and are "
                        "the endpoint and --run right?"
                        + ("" if next_put else " (nothing was published)"), status=1)
                who = f"agent {dst}" if dst is not None else "the agents"
                state = "not alive" if dst is not None and dst not in alive else \
                    "did not confirm"
                raise InputError(f"{who} {state} within {timeout:g} s (run {net.run!r})",
                                 status=1)
            peer.wait(timeout=0.1)

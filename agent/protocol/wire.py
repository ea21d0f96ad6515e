"""The messages of a socmon run: schemas of the sensors, truth, estimate, status and control
messages, built on the msgpack codec of :mod:`broker_free_net.codec`.

Every message is a msgpack map with str keys, ``"v": 1`` and a ``"kind"`` naming it.
float64 arrays travel as ``{"dtype": "<f8", "shape": [...], "data": <bin>}``; maps keyed
by agent id use the decimal id as a str key (msgpack map keys must be strings here).
Agents are numbered 1..M (M = active + standby agents). The full wire format, key by key,
is in docs/runtime.md.

Examples
--------
>>> import numpy as np
>>> payload = encode_est(2, 7, np.zeros(3), epoch=0, t=1.5)
>>> msg = decode(payload, est_schema(3))
>>> msg["agent"], msg["step"], msg["x"].shape
(2, 7, (3,))
"""

from __future__ import annotations

import math

import numpy as np

from broker_free_net.codec import (
    MAX_DEPTH,
    Bool,
    Bytes,
    F64Array,
    Float,
    Int,
    MalformedMessage,
    Schema,
    Str,
    decode,
    encode,
)

__all__ = [
    "MAX_STEP",
    "AgentIds",
    "StrList",
    "WeightMap",
    "IntMap",
    "Loose",
    "ResidualTests",
    "sensors_schema",
    "truth_schema",
    "est_schema",
    "ctl_schema",
    "roster_schema",
    "STATUS_SCHEMA",
    "END_SCHEMA",
    "END_REASONS",
    "encode_end",
    "MONITOR_EVENT_SCHEMA",
    "encode_monitor_event",
    "encode_sensors",
    "encode_truth",
    "encode_est",
    "encode_ctl",
    "encode_roster",
    "encode_status",
    "decode",
    "MalformedMessage",
]

#: Largest step stamp accepted on the wire (about 8 years at 1 ms per step).
MAX_STEP = 2**38
#: Stamps farther than this from the receiver's step are refused ("stale"/"future"): the
#: one stamp window of every key (the agents' sensors and estimates, the recorder's truth
#: and estimates; docs/runtime.md).
STAMP_WINDOW = 100_000
#: Agent ids on the wire: 1..MAX_AGENT.
MAX_AGENT = 100_000
#: A free-form field's value nests at most this many containers (the codec's MAX_DEPTH
#: below the message's top map).
LOOSE_MAX_DEPTH = MAX_DEPTH - 1


class StrList:
    """A list of distinct short strings (node labels), at most ``max_len`` of them."""

    bounded_depth = True    # a container of scalars (codec.UNSCANNED_MAX_BYTES)

    def __init__(self, max_len: int = 4096, required: bool = True):
        self.max_len = max_len
        self.required = required

    def check(self, name, value):
        if not isinstance(value, list):
            raise MalformedMessage("type", f"expected a list, got {type(value).__name__}", name)
        if len(value) > self.max_len:
            raise MalformedMessage("range", f"more than {self.max_len} items", name)
        for item in value:
            if not isinstance(item, str) or not 0 < len(item) <= 256:
                raise MalformedMessage("type", f"items must be non-empty strings, got {item!r}", name)
        if len(set(value)) != len(value):
            raise MalformedMessage("range", "duplicate items", name)
        return list(value)


class AgentIds:
    """A list of distinct agent ids (ints in 1..MAX_AGENT)."""

    bounded_depth = True    # a container of scalars (codec.UNSCANNED_MAX_BYTES)

    required = True

    def __init__(self, required: bool = True):
        self.required = required

    def check(self, name, value):
        if not isinstance(value, list) or len(value) > 4096:
            raise MalformedMessage("type", "expected a list of agent ids", name)
        for item in value:
            if isinstance(item, bool) or not isinstance(item, int) or not 1 <= item <= MAX_AGENT:
                raise MalformedMessage("range", f"bad agent id {item!r}", name)
        return list(value)


def _agent_key(name, key) -> int:
    if not isinstance(key, str) or not key.isascii() or not key.isdigit() or key != str(int(key)):
        raise MalformedMessage("type", f"map key {key!r} is not a decimal agent id", name)
    a = int(key)
    if not 1 <= a <= MAX_AGENT:
        raise MalformedMessage("range", f"agent id {a} outside 1..{MAX_AGENT}", name)
    return a


class WeightMap:
    """``{"<agent id>": weight}`` with finite weights in [0, 1]; decodes to ``{int: float}``."""

    bounded_depth = True    # a container of scalars (codec.UNSCANNED_MAX_BYTES)

    def __init__(self, required: bool = True):
        self.required = required

    def check(self, name, value):
        if not isinstance(value, dict) or len(value) > 4096:
            raise MalformedMessage("type", "expected a map agent id -> weight", name)
        out = {}
        for key, w in value.items():
            a = _agent_key(name, key)
            if isinstance(w, bool) or not isinstance(w, (int, float)):
                raise MalformedMessage("type", f"weight of agent {a} is not a number", name)
            w = float(w)
            if not math.isfinite(w):
                raise MalformedMessage("nonfinite", f"weight of agent {a} is not finite", name)
            if not 0.0 <= w <= 1.0:
                raise MalformedMessage("range", f"weight of agent {a} = {w} outside [0, 1]", name)
            out[a] = w
        return out


class IntMap:
    """``{str: int}`` (counters, learned delays); decodes to a dict."""

    bounded_depth = True    # a container of scalars (codec.UNSCANNED_MAX_BYTES)

    def __init__(self, agent_keys: bool = False, required: bool = True):
        self.agent_keys = agent_keys
        self.required = required

    def check(self, name, value):
        if not isinstance(value, dict) or len(value) > 4096:
            raise MalformedMessage("type", "expected a map", name)
        out = {}
        for key, v in value.items():
            k = _agent_key(name, key) if self.agent_keys else key
            if not isinstance(k, (str, int)) or isinstance(v, bool) or not isinstance(v, int):
                raise MalformedMessage("type", f"entry {key!r} is not str -> int", name)
            out[k] = v
        return out


class Loose:
    """Any msgpack value (free-form, for informational status fields) nested at most
    :data:`LOOSE_MAX_DEPTH` containers deep (what the codec's header walk allows below the
    message's top map, checked here for a payload decoded without it)."""

    bounded_depth = True

    def __init__(self, required: bool = False):
        self.required = required

    def check(self, name, value):
        if isinstance(value, (dict, list)):
            level, deepest = [value], 1
            while level:
                if deepest > LOOSE_MAX_DEPTH:
                    raise MalformedMessage("too_deep", "containers nested deeper than "
                                           f"{LOOSE_MAX_DEPTH}", name)
                level = [v for c in level for v in (c.values() if isinstance(c, dict) else c)
                         if isinstance(v, (dict, list))]
                deepest += 1 if level else 0
        return value


class ResidualTests:
    """An assignment's ``residuals``: the receiving agent's residual tests of the new
    configuration (:meth:`design.residuals.AgentTests.to_wire`). Checks the structure and
    the types, decodes the arrays; the agent checks them against its role
    (:meth:`design.residuals.AgentTests.from_wire`)."""

    bounded_depth = True    # a map of lists of maps of arrays (4 deep)

    _TEST = {"from": Int(0, MAX_AGENT), "age": Int(0, MAX_STEP), "whiten": F64Array((None, None)),
             "alpha": Float(0.0, 1.0), "threshold": Float(0.0, 1e300),
             "null": F64Array((None, None), required=False),
             "null_floor": Float(0.0, 1e300, required=False),
             "null_threshold": Float(0.0, 1e300, required=False)}
    MAX_TESTS = 1025

    def __init__(self, required: bool = False):
        self.required = required

    def check(self, name, value):
        if not isinstance(value, dict) or set(value) != {"window", "warmup", "tests"}:
            raise MalformedMessage("type", "expected a map of window, warmup and tests", name)
        out = {"window": Int(1, 4096).check(f"{name}.window", value["window"]),
               "warmup": Int(0, MAX_STEP).check(f"{name}.warmup", value["warmup"]), "tests": []}
        tests = value["tests"]
        if not isinstance(tests, list) or not 0 < len(tests) <= self.MAX_TESTS:
            raise MalformedMessage("type", f"tests: expected a list of 1..{self.MAX_TESTS} "
                                   "tests", name)
        for i, t in enumerate(tests):
            where = f"{name}.tests[{i}]"
            if not isinstance(t, dict) or not set(t) <= set(self._TEST) \
                    or not {k for k, spec in self._TEST.items() if spec.required} <= set(t):
                raise MalformedMessage("type", "expected a map of from, age, whiten, alpha, "
                                       "threshold and optionally null, null_floor and "
                                       "null_threshold", where)
            out["tests"].append({k: self._TEST[k].check(f"{where}.{k}", v)
                                 for k, v in t.items()})
        return out


_STEP = Int(0, MAX_STEP)
#: an authenticated control message: signer's sequence and Ed25519 signature
#: (agent.protocol.control_auth)
_SIGNED = {"seq": Int(1, 2**62, required=False), "sig": Bytes(64, required=False)}
_AGENT = Int(1, MAX_AGENT)


def sensors_schema(n: int) -> Schema:
    """``socmon/<run>/sensors``: the state of every node at one step, in the scenario's node
    order (world -> agents; each agent reads its own nodes' entries)."""
    return Schema({"kind": Str(choices=frozenset({"sensors"})), "step": _STEP,
                   "x": F64Array((n,))}, stamp="step")


def truth_schema(n: int) -> Schema:
    """``socmon/<run>/truth``: the whole true state (world -> recorder/monitor only)."""
    return Schema({"kind": Str(choices=frozenset({"truth"})), "step": _STEP,
                   "x": F64Array((n,))}, stamp="step")


def est_schema(n: int) -> Schema:
    """``socmon/<run>/est/<agent>``: an agent's posterior estimate at a step."""
    return Schema({"kind": Str(choices=frozenset({"est"})), "agent": _AGENT, "step": _STEP,
                   "epoch": Int(0, 2**62), "t": Float(0.0, 1e12), "x": F64Array((n,))},
                  stamp="step", sender="agent")


#: Why the world ended: its last step was done, or it was stopped (SIGTERM/SIGINT), or its
#: state overflowed float64.
END_REASONS = ("steps", "stopped", "overflow")
#: ``socmon/<run>/end``: the world's last step, published once when it ends. Without it a
#: world whose token went was paused or cut off, not finished.
END_SCHEMA = Schema({"kind": Str(choices=frozenset({"end"})), "step": Int(-1, MAX_STEP),
                     "reason": Str(choices=frozenset(END_REASONS))})


def ctl_schema(n: int) -> Schema:
    """``socmon/<run>/ctl/<agent>``: a role assignment."""
    return Schema({
        "kind": Str(choices=frozenset({"assign"})),
        "agent": _AGENT,
        "epoch": Int(1, 2**62),
        "activate_at": _STEP,
        "measure": StrList(),
        "neighbours": WeightMap(),
        "self_weight": Float(0.0, 1.0),
        "gain": F64Array((n, None)),
        "take_over": Int(1, MAX_AGENT, required=False),
        # new neighbour -> the failed agent whose stream it continues (design.estimator's
        # continuity rule); optional: an assignment without it continues nothing
        "continues": IntMap(agent_keys=True, required=False),
        # the agent's residual tests of the new configuration (design.residuals.
        # AgentTests.to_wire); optional: without it the agent's tests are off from the switch
        "residuals": ResidualTests(required=False),
        **_SIGNED,
    })


def roster_schema() -> Schema:
    """``socmon/<run>/ctl/0``: the ids in force from ``activate_at`` (the monitor's fence)."""
    return Schema({
        "kind": Str(choices=frozenset({"roster"})),
        "epoch": Int(1, 2**62),
        "activate_at": _STEP,
        "ids": AgentIds(),
        # the convicted agents on probation, and of them those never to rejoin: what a
        # monitor adopting this roster keeps out of the standbys; optional (none)
        "probation": AgentIds(required=False),
        "barred": AgentIds(required=False),
        **_SIGNED,
    })


STATUS_SCHEMA = Schema({
    "kind": Str(choices=frozenset({"status"})),
    "agent": _AGENT,
    "step": Int(-1, MAX_STEP),
    "active": Bool(),
    "epoch": Int(0, 2**62),
    "measure": StrList(),
    "neighbours": WeightMap(),
    "delays": IntMap(agent_keys=True),
    "drops": Int(0),
    "late": Int(0),
    "inputs": IntMap(required=False),
    "ages": IntMap(agent_keys=True, required=False),
    "fenced": Int(0, required=False),
    "roster_epoch": Int(0, 2**62, required=False),
    "malformed": Int(0),
    "malformed_reasons": IntMap(),
    "impaired": Int(0),
    "sensor": Loose(required=True),
    # the agents whose status it heard: the start handshake, sent until the clock starts
    "heard": AgentIds(required=False),
    # the run seed it was started with (sent with "heard") and the digest of the gain it
    # started with (design.gains.gain_digest, while it runs epoch 0's role): for the world
    # and the monitor to check against theirs
    "seed": Int(0, 2**63 - 1, required=False),   # a larger seed is not sent
    "gains": Str(max_len=64, required=False),
    "ctl": Loose(required=True),
    "links": Loose(required=True),
    "overflows": Int(0),
    "hop_ms": Loose(required=False),
    # whose estimates the agent subscribes to ("*": every agent), the changes and the
    # longest declaration of them (agent.node.subscriptions)
    "estimates_from": Loose(required=False),
    "implausible": Loose(required=False),
    "residuals": Loose(required=False),
}, sender="agent")


def _f(x) -> float:
    return float(x)


def max_est_bytes(n: int) -> int:
    """A bound on the size of a valid estimate message of an ``n``-state scenario.

    The largest message :func:`est_schema` accepts (every field at its widest encoding),
    doubled: an agent's estimate inbox refuses anything larger before copying it out of
    zenoh, so junk on an estimate key never occupies more than this per message.

    >>> max_est_bytes(14) < 1024 < max_est_bytes(100)
    True
    """
    return 2 * len(encode_est(MAX_AGENT, MAX_STEP, np.full(n, -1.0e300), 2**62 - 1, 1e12 - 1))


def max_sensors_bytes(n: int) -> int:
    """A bound on the size of a valid sensors message of an ``n``-state scenario, doubled
    (see :func:`max_est_bytes`)."""
    return 2 * len(encode_sensors(MAX_STEP, np.full(n, -1.0e300)))


def encode_sensors(step: int, x) -> bytes:
    return encode({"kind": "sensors", "step": int(step), "x": np.asarray(x, dtype=float)})


def encode_truth(step: int, x) -> bytes:
    return encode({"kind": "truth", "step": int(step), "x": np.asarray(x, dtype=float)})


def encode_est(agent: int, step: int, x, epoch: int, t: float) -> bytes:
    return encode({"kind": "est", "agent": int(agent), "step": int(step), "epoch": int(epoch),
                   "t": _f(t), "x": np.asarray(x, dtype=float)})


def encode_ctl(agent: int, epoch: int, activate_at: int, measure, neighbours: dict,
               self_weight: float, gain, take_over: int | None = None, signer=None,
               continues: dict | None = None,
               run: str | None = None, residuals: dict | None = None) -> bytes:
    """Encode a role assignment; ``neighbours`` maps agent id (int) -> weight.

    With ``signer`` (:class:`agent.protocol.control_auth.ControlSigner`) and ``run``, the message
    is signed as it will be decoded."""
    msg = {"kind": "assign", "agent": int(agent), "epoch": int(epoch),
           "activate_at": int(activate_at), "measure": [str(m) for m in measure],
           "neighbours": {int(a): _f(w) for a, w in neighbours.items()},
           "self_weight": _f(self_weight), "gain": np.asarray(gain, dtype=float)}
    if take_over is not None:
        msg["take_over"] = int(take_over)
    if continues:
        msg["continues"] = {int(a): int(f) for a, f in continues.items()}
    if residuals is not None:
        msg["residuals"] = residuals
    if signer is not None:
        msg = signer.sign(msg, run)
    msg["neighbours"] = {str(a): w for a, w in msg["neighbours"].items()}
    if "continues" in msg:
        msg["continues"] = {str(a): f for a, f in msg["continues"].items()}
    return encode(msg)


def encode_roster(epoch: int, activate_at: int, ids, signer=None, run: str | None = None,
                  probation=(), barred=()) -> bytes:
    msg = {"kind": "roster", "epoch": int(epoch), "activate_at": int(activate_at),
           "ids": [int(a) for a in ids]}
    if probation:
        msg["probation"] = [int(a) for a in probation]
    if barred:
        msg["barred"] = [int(a) for a in barred]
    return encode(msg if signer is None else signer.sign(msg, run))


def encode_end(step: int, reason: str) -> bytes:
    return encode({"kind": "end", "step": int(step), "reason": str(reason)})


def encode_status(status: dict) -> bytes:
    msg = dict(status)
    msg["kind"] = "status"
    msg["neighbours"] = {str(a): _f(w) for a, w in status["neighbours"].items()}
    msg["delays"] = {str(a): int(d) for a, d in status["delays"].items()}
    if "ages" in status:
        msg["ages"] = {str(a): int(d) for a, d in status["ages"].items()}
    return encode(msg)


#: ``socmon/<run>/monitor/events``: one record of the monitor's events file (its verdicts,
#: reassignments, confirmations; docs/monitor.md) as its JSON text, for watchers.
MONITOR_EVENT_SCHEMA = Schema({"kind": Str(choices=frozenset({"monitor_event"})),
                               "event": Str(max_len=1 << 16)})


def encode_monitor_event(record: dict) -> bytes:
    """One monitor event (a JSON-able map with a str ``kind``) for the wire."""
    import json

    return encode({"kind": "monitor_event", "event": json.dumps(record)})

"""Per-link impairments applied at the receiver.

A link is a directed pair ``(src, dst)`` of opaque hashable ids. Each link
may have a delay (in steps, or in milliseconds with uniform jitter), a drop
probability (independent Bernoulli, or bursty Gilbert-Elliott), and a
partition flag.

Impairments are applied by the RECEIVER, when a message arrives:

* the receiver knows its own clock and step, so "deliver at step S" or
  "deliver at time T" is evaluated exactly where the message is consumed;
* a partition is simply "the receiver drops everything from src";
* the sender need not cooperate, so an impairment holds even against a
  foreign or misbehaving client publishing on the run's keys.

Everything here is pure and deterministic given the seed, the sequence of
calls and the clock values passed in (or the injected ``clock``). Each link
has its own random stream derived from ``(seed, src, dst)``, so the outcome
on one link does not depend on traffic on others.

Order of checks on arrival: partition -> drop -> delay.
"""

from __future__ import annotations

import math
import random
import time
from dataclasses import dataclass, replace
from typing import Any, Callable, Hashable, NamedTuple

from .codec import Bool, Bytes, Float, Ident, Int, MalformedMessage, Schema, Str, decode, encode

__all__ = [
    "DELIVER",
    "DROP",
    "HOLD",
    "IMPAIR_SCHEMA",
    "Decision",
    "InvalidImpairment",
    "LinkImpairments",
    "LinkParams",
    "apply_impairment_message",
    "decode_impairment",
    "encode_impairment",
]

DROP = "drop"
DELIVER = "deliver"
HOLD = "hold"


class InvalidImpairment(ValueError):
    """An impairment parameter is invalid; ``field`` names it."""

    def __init__(self, field: str, message: str):
        self.field = field
        super().__init__(f"{field}: {message}")


@dataclass(frozen=True)
class LinkParams:
    """Impairment of one directed link.

    Parameters
    ----------
    delay_steps : int
        Hold a message until the receiver's step reaches ``stamp + delay_steps``.
    delay_ms : float
        Hold a message for ``delay_ms`` (+ jitter) milliseconds after arrival.
    jitter_ms : float
        Extra delay drawn uniformly in ``[0, jitter_ms]`` per message. Jitter
        may reorder messages; step delays never do.
    drop : float
        Long-run fraction of messages dropped, in ``[0, 1]``.
    burst : float or None
        ``None``: independent (Bernoulli) drops. A number ``>= 1``: bursty
        drops from a two-state Gilbert-Elliott chain (good state never drops,
        bad state always drops) whose mean burst length is `burst`.
    partition : bool
        Drop everything on the link.
    """

    delay_steps: int = 0
    delay_ms: float = 0.0
    jitter_ms: float = 0.0
    drop: float = 0.0
    burst: float | None = None
    partition: bool = False

    def __post_init__(self):
        if isinstance(self.delay_steps, bool) or not isinstance(self.delay_steps, int) or self.delay_steps < 0:
            raise InvalidImpairment("delay_steps", f"expected int >= 0, got {self.delay_steps!r}")
        for name in ("delay_ms", "jitter_ms"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not (0 <= value < math.inf):
                raise InvalidImpairment(name, f"expected finite number >= 0, got {value!r}")
        if isinstance(self.drop, bool) or not isinstance(self.drop, (int, float)) or not 0 <= self.drop <= 1:
            raise InvalidImpairment("drop", f"expected probability in [0, 1], got {self.drop!r}")
        if self.burst is not None:
            if isinstance(self.burst, bool) or not isinstance(self.burst, (int, float)) \
                    or not 1 <= self.burst < math.inf:
                raise InvalidImpairment("burst", f"expected mean burst length >= 1 or None, got {self.burst!r}")
            if self.drop >= 1:
                raise InvalidImpairment("drop", "drop=1 with burst: use partition instead")
            if self.enter_bad > 1:
                raise InvalidImpairment(
                    "burst", f"drop={self.drop} too high for burst={self.burst}: need drop <= burst/(burst+1)")
        if not isinstance(self.partition, bool):
            raise InvalidImpairment("partition", f"expected bool, got {self.partition!r}")

    @property
    def leave_bad(self) -> float:
        """Gilbert-Elliott P(bad -> good) = 1 / burst."""
        return 1.0 / self.burst

    @property
    def enter_bad(self) -> float:
        """Gilbert-Elliott P(good -> bad) so that the stationary drop rate is `drop`."""
        r = self.leave_bad
        return self.drop * r / (1.0 - self.drop)

    @property
    def is_identity(self) -> bool:
        """True if the link is not impaired at all."""
        return self == _IDENTITY


#: the parameters of a link that is not impaired (frozen: shared, not built per message)
_IDENTITY = LinkParams()


class Decision(NamedTuple):
    """Outcome of :meth:`LinkImpairments.offer`.

    ``action`` is :data:`DROP`, :data:`DELIVER` or :data:`HOLD`; for a hold,
    ``due_step`` and/or ``due_time`` say when the message will be released.
    """

    action: str
    due_step: int | None = None
    due_time: float | None = None


class _Held(NamedTuple):
    due_step: int | None
    due_time: float | None
    seq: int
    src: Any
    dst: Any
    message: Any


class _LinkState:
    __slots__ = ("params", "rng", "bad")

    def __init__(self, params: LinkParams, rng: random.Random):
        self.params = params
        self.rng = rng
        self.bad = False


class LinkImpairments:
    """Table of per-link impairments with a hold queue.

    Parameters
    ----------
    seed : int
        Seed of the per-link random streams.
    clock : callable, optional
        Returns the current time in seconds; used when a millisecond delay
        applies and no explicit time is given. Default ``time.monotonic``.

    Examples
    --------
    >>> table = LinkImpairments(seed=1)
    >>> _ = table.set((0, 1), delay_steps=2)
    >>> table.offer(0, 1, "m", stamp_step=5)
    Decision(action='hold', due_step=7, due_time=None)
    >>> table.release(now_step=7)
    [(0, 1, 'm')]
    """

    def __init__(self, seed: int = 0, clock: Callable[[], float] = time.monotonic):
        self.seed = seed
        self.clock = clock
        self._links: dict[Hashable, _LinkState] = {}
        self._held: list[_Held] = []
        self._seq = 0

    # -- table ---------------------------------------------------------------

    def set(self, link: tuple, **params) -> LinkParams:
        """Update the impairment of `link` = ``(src, dst)``.

        Only the given parameters change; the others keep their current
        values (so a delay and a drop rate can be injected separately).
        Returns the new :class:`LinkParams`.
        """
        link = self._check_link(link)
        unknown = set(params) - set(LinkParams.__dataclass_fields__)
        if unknown:
            raise InvalidImpairment(sorted(unknown)[0], "unknown impairment parameter")
        state = self._links.get(link)
        new = replace(state.params if state else LinkParams(), **params)
        if state is None:
            self._links[link] = _LinkState(new, random.Random(f"{self.seed}:{link[0]!r}:{link[1]!r}"))
        else:
            if new.burst != state.params.burst:
                state.bad = False
            state.params = new
        return new

    def clear(self, link: tuple) -> None:
        """Remove every impairment of `link` (held messages stay held)."""
        self._links.pop(self._check_link(link), None)

    def clear_all(self) -> None:
        """Remove every impairment of every link (held messages stay held)."""
        self._links.clear()

    def get(self, link: tuple) -> LinkParams:
        """Return the current parameters of `link` (identity if none)."""
        state = self._links.get(self._check_link(link))
        return state.params if state else _IDENTITY

    def links(self) -> dict:
        """Return ``{link: LinkParams}`` of every impaired link."""
        return {link: s.params for link, s in self._links.items()}

    @staticmethod
    def _check_link(link) -> tuple:
        if not isinstance(link, tuple) or len(link) != 2:
            raise InvalidImpairment("link", f"expected a (src, dst) tuple, got {link!r}")
        hash(link)
        return link

    # -- filtering -----------------------------------------------------------

    def offer(self, src, dst, message, *, stamp_step: int | None = None,
              arrival: float | None = None) -> Decision:
        """Filter one arriving message.

        Parameters
        ----------
        src, dst : hashable
            The link the message travelled on (dst is the receiver).
        message : object
            Anything; returned unchanged by :meth:`release` if held.
        stamp_step : int, optional
            The sender's step stamped in the message; required if the link
            has a step delay.
        arrival : float, optional
            Arrival time in seconds; default ``clock()``. Used for ms delays.

        Returns
        -------
        Decision
            :data:`DROP` (gone), :data:`DELIVER` (use it now) or :data:`HOLD`
            (kept; comes out of :meth:`release` when due).
        """
        state = self._links.get((src, dst))
        if state is None:
            return Decision(DELIVER)
        p = state.params
        if p.partition:
            return Decision(DROP)
        if p.drop > 0 and self._draw_drop(state):
            return Decision(DROP)
        due_step = due_time = None
        if p.delay_steps:
            if stamp_step is None:
                raise InvalidImpairment("stamp_step", f"link {(src, dst)!r} has a step delay but no stamp was given")
            due_step = stamp_step + p.delay_steps
        if p.delay_ms or p.jitter_ms:
            t = self.clock() if arrival is None else arrival
            jitter = state.rng.uniform(0.0, p.jitter_ms) if p.jitter_ms else 0.0
            due_time = t + (p.delay_ms + jitter) / 1000.0
        if due_step is None and due_time is None:
            return Decision(DELIVER)
        self._held.append(_Held(due_step, due_time, self._seq, src, dst, message))
        self._seq += 1
        return Decision(HOLD, due_step, due_time)

    def _draw_drop(self, state: _LinkState) -> bool:
        p, rng = state.params, state.rng
        if p.burst is None:
            return rng.random() < p.drop
        # Gilbert-Elliott: move the chain, then drop iff in the bad state.
        if state.bad:
            state.bad = rng.random() >= p.leave_bad
        else:
            state.bad = rng.random() < p.enter_bad
        return state.bad

    def release(self, now_step: int | None = None, now_time: float | None = None) -> list[tuple]:
        """Return the held messages that are due, as ``(src, dst, message)``.

        A message is due when ``now_step >= due_step`` (if it has a step
        delay) and ``now_time >= due_time`` (if it has a ms delay;
        `now_time` defaults to ``clock()``). A message with a step delay is
        never due while `now_step` is None. Due messages come out ordered by
        due step, then due time, then arrival order.
        """
        if not self._held:
            return []
        if now_time is None and any(h.due_time is not None for h in self._held):
            now_time = self.clock()
        due, keep = [], []
        for h in self._held:
            step_ok = h.due_step is None or (now_step is not None and now_step >= h.due_step)
            time_ok = h.due_time is None or now_time >= h.due_time
            (due if step_ok and time_ok else keep).append(h)
        self._held = keep
        due.sort(key=lambda h: (h.due_step if h.due_step is not None else -math.inf,
                                h.due_time if h.due_time is not None else -math.inf, h.seq))
        return [(h.src, h.dst, h.message) for h in due]

    @property
    def held(self) -> int:
        """Number of messages currently held."""
        return len(self._held)


# --------------------------------------------------------------------------
# impairment-change messages (published on socmon/<run>/impair)

IMPAIR_OPS = ("set", "clear", "clear_all")

#: Wire schema of an impairment change. ``src``/``dst`` are required for
#: "set" and "clear"; the parameters only for "set" (absent = unchanged).
IMPAIR_SCHEMA = Schema({
    "kind": Str(choices=frozenset({"impair"})),
    "op": Str(choices=frozenset(IMPAIR_OPS)),
    "src": Ident(required=False),
    "dst": Ident(required=False),
    "delay_steps": Int(0, 1_000_000, required=False),
    "delay_ms": Float(0.0, 3_600_000.0, required=False),
    "jitter_ms": Float(0.0, 3_600_000.0, required=False),
    "drop": Float(0.0, 1.0, required=False),
    "burst": Float(1.0, 1e6, required=False),
    "partition": Bool(required=False),
    # an authenticated change carries its signer's sequence number and signature; they
    # are opaque here (the agent checks them)
    "seq": Int(1, 2**62, required=False),
    "sig": Bytes(64, required=False),
})
_PARAM_NAMES = ("delay_steps", "delay_ms", "jitter_ms", "drop", "burst", "partition")


def encode_impairment(op: str, src=None, dst=None, sign=None, **params) -> bytes:
    """Encode an impairment change.

    Parameters
    ----------
    op : {"set", "clear", "clear_all"}
    src, dst : int or str
        The directed link (not for "clear_all").
    sign : callable, optional
        ``sign(msg) -> msg`` adds authentication fields (``seq``, ``sig``) to the
        message as it will be decoded.
    **params
        For "set": any of ``delay_steps, delay_ms, jitter_ms, drop, burst,
        partition``. ``burst=None`` is sent as "absent" (unchanged).

    Examples
    --------
    >>> payload = encode_impairment("set", 0, 3, delay_steps=2, drop=0.1)
    """
    msg = {"kind": "impair", "op": op}
    if src is not None:
        msg["src"] = src
    if dst is not None:
        msg["dst"] = dst
    msg.update({k: v for k, v in params.items() if v is not None})
    if sign is not None:
        msg = sign(msg)
    payload = encode(msg)
    _check_impairment(decode(payload, IMPAIR_SCHEMA))  # fail at the sender, not at every receiver
    return payload


def _check_impairment(msg: dict) -> dict:
    op = msg["op"]
    if op in ("set", "clear"):
        for name in ("src", "dst"):
            if name not in msg:
                raise MalformedMessage("missing", f"required for op {op!r}", name)
    params = {k: msg[k] for k in _PARAM_NAMES if k in msg}
    if op != "set" and params:
        raise MalformedMessage("extra", f"parameters not allowed for op {op!r}", sorted(params)[0])
    if op == "set":
        try:
            LinkParams(**params)
        except InvalidImpairment as exc:
            raise MalformedMessage("range", str(exc), exc.field) from None
    return msg


def decode_impairment(payload) -> dict:
    """Decode and validate an impairment change; raises ``MalformedMessage``."""
    return _check_impairment(decode(payload, IMPAIR_SCHEMA))


def apply_impairment_message(table: LinkImpairments, msg: dict) -> None:
    """Apply a decoded impairment change to `table`.

    "set" merges the given parameters into the link's current ones; "clear"
    resets one link; "clear_all" resets every link. Parameters that are
    valid alone but not together with the link's current ones (e.g. a high
    drop rate added to a bursty link) raise :class:`InvalidImpairment` and
    leave the table unchanged.
    """
    op = msg["op"]
    if op == "set":
        table.set((msg["src"], msg["dst"]), **{k: msg[k] for k in _PARAM_NAMES if k in msg})
    elif op == "clear":
        table.clear((msg["src"], msg["dst"]))
    elif op == "clear_all":
        table.clear_all()
    else:
        raise InvalidImpairment("op", f"unknown op {op!r}")

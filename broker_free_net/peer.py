"""One zenoh session per process, with a liveliness token and inboxes.

Threading model: zenoh calls subscriber callbacks on its own threads. Our
callbacks only copy ``(payload bytes, key, arrival time)`` into a bounded
:class:`Inbox` (drop-oldest on overflow, counted) and notify a condition;
they never call zenoh and never block beyond a short lock. The owning thread
reads with :meth:`Inbox.poll` / :meth:`Inbox.get` / :meth:`Inbox.drain` and
does all decoding and publishing.

Processes: never ``fork`` after a session is open (zenoh's runtime threads
do not survive it). Start socmon processes with ``subprocess`` or the
``spawn`` multiprocessing context. A :class:`Peer` used from a forked child
raises ``RuntimeError`` and its close() there does nothing.
"""

from __future__ import annotations

import atexit
import logging
import os
import threading
import time
from collections import deque
from typing import Callable, NamedTuple

import zenoh
import zenoh.ext

from . import keys
from .codec import MAX_PAYLOAD_BYTES
from .config import NetConfig, build_zenoh_config, zenoh_message
from .linger import LingerGuard

__all__ = ["IdInUse", "Inbox", "KeySetInbox", "LivelinessEvent", "LivelinessWatch", "Peer", "Received",
           "SessionError"]

DEFAULT_INBOX_SIZE = 4096
#: Payload bytes an inbox holds at most (the oldest items are dropped beyond it).
DEFAULT_INBOX_BYTES = 4 << 20
_log = logging.getLogger(__name__)
#: zenoh priorities a publisher may be declared with (highest first)
_PRIORITIES = ("REAL_TIME", "INTERACTIVE_HIGH", "INTERACTIVE_LOW", "DATA_HIGH", "DATA",
               "DATA_LOW", "BACKGROUND")


class IdInUse(zenoh.ZError):
    """Another session holds the liveliness token of this process's ``(role, id)``: two
    processes would speak for one id (:meth:`Peer.claim`)."""

    def __init__(self, peer, others):
        super().__init__(
            f"{peer.role} {peer.id} of run {peer.run} is already running (session "
            f"{', '.join(sorted(others))} holds its liveliness token): two processes with "
            "one id would publish the same keys; stop the other one first")
        self.others = frozenset(others)


class SessionError(zenoh.ZError):
    """A zenoh session could not be opened: zenoh's reason, with the endpoints it was
    asked to listen on and connect to (a secured process, or a client of one router,
    gives up on its connect endpoints after a timeout; a listen port may be taken)."""

    def __init__(self, net, reason: str):
        where = "; ".join(f"{what} {', '.join(eps)}" for what, eps
                          in (("listen on", net.listen), ("connect to", net.connect)) if eps)
        super().__init__(f"cannot open the zenoh session ({where or 'scouting only'}): "
                         f"{reason}")


class Received(NamedTuple):
    """A sample as queued by a subscriber callback."""

    payload: bytes
    key: str
    arrival: float  # time.monotonic() at enqueue


class LivelinessEvent(NamedTuple):
    """A process's token appeared (``alive=True``) or went (``alive=False``).

    Every process declares its token under its own session's zid, so two processes
    claiming one ``(role, id)`` are two tokens: ``sessions`` holds the zids whose token
    for ``(role, id)`` is alive after this event, and :attr:`any_alive` says whether any
    is (what a process that only wants to know "is agent 3 there" reads).
    """

    role: str
    id: str
    alive: bool
    key: str
    arrival: float
    session: str = ""
    sessions: frozenset = frozenset()

    @property
    def any_alive(self) -> bool:
        """Whether some process holds a token for ``(role, id)`` after this event."""
        return bool(self.sessions)


def _check_bound(name, value, lo):
    if isinstance(value, bool) or not isinstance(value, int) or value < lo:
        raise ValueError(f"{name}: expected int >= {lo}, got {value!r}")


def _size_of(item) -> int:
    payload = getattr(item, "payload", None)
    return len(payload) if isinstance(payload, (bytes, bytearray)) else 0


def _feeder(inbox):
    """The subscriber callback that copies a sample into ``inbox`` (never raises into
    zenoh; DELETE samples and oversized payloads are counted, not queued)."""

    def on_sample(sample):
        try:
            if sample.kind != zenoh.SampleKind.PUT:
                inbox._ignore()
                return
            if len(sample.payload) > inbox.max_payload:
                inbox._refuse_oversized()
                return
            inbox._push(Received(sample.payload.to_bytes(), str(sample.key_expr),
                                 time.monotonic()))
        except Exception:  # never raise into zenoh
            inbox._ignore()

    return on_sample


class Inbox:
    """Bounded, thread-safe FIFO filled by a zenoh callback.

    Bounded by count (`maxlen` items) and by size (`max_bytes` payload bytes, counting
    :attr:`Received.payload`): beyond either bound the oldest items are dropped and
    counted in :attr:`overflows`. A payload larger than `max_payload` is refused by the
    subscriber callback before it is copied out of zenoh, and counted in
    :attr:`oversized`.

    Attributes
    ----------
    received : int
        Items enqueued so far (including those later dropped by overflow).
    overflows : int
        Items dropped because the inbox was full (by count or by bytes).
    oversized : int
        Samples refused because their payload exceeded `max_payload` bytes.
    ignored : int
        Samples the callback discarded (DELETE samples on data keys, bad
        liveliness keys, internal errors).
    nbytes : int
        Payload bytes currently held.
    wakes : bool or set of str
        Whether an item arriving wakes :meth:`Peer.wait` (default True), or the keys whose
        items do. The owner may narrow it while it does not need the other items at
        once; it widens it *before* checking ``len(inbox)``, so that an item that
        arrived in between is never waited on.
    """

    def __init__(self, maxlen: int = DEFAULT_INBOX_SIZE, wakeup: threading.Event | None = None,
                 max_bytes: int = DEFAULT_INBOX_BYTES, max_payload: int = MAX_PAYLOAD_BYTES):
        _check_bound("maxlen", maxlen, 1)
        _check_bound("max_payload", max_payload, 0)
        _check_bound("max_bytes", max_bytes, max(1, max_payload))
        self.maxlen = maxlen
        self.max_bytes = max_bytes
        self.max_payload = max_payload
        self._items: deque = deque()
        self._cond = threading.Condition(threading.Lock())
        self.received = 0
        self.overflows = 0
        self.oversized = 0
        self.ignored = 0
        self.nbytes = 0
        self._subscriber = None
        self._wakeup = wakeup
        self.wakes = True

    # called from zenoh threads -------------------------------------------------
    def _push(self, item) -> None:
        size = _size_of(item)
        with self._cond:
            if size > self.max_payload:
                self.oversized += 1
                return
            while self._items and (len(self._items) >= self.maxlen
                                   or self.nbytes + size > self.max_bytes):
                self.nbytes -= _size_of(self._items.popleft())
                self.overflows += 1
            self._items.append(item)
            self.nbytes += size
            self.received += 1
            self._cond.notify()
        wakes = self.wakes
        if self._wakeup is not None and (
                wakes if isinstance(wakes, bool) else getattr(item, "key", None) in wakes):
            self._wakeup.set()

    def _refuse_oversized(self) -> None:
        with self._cond:
            self.oversized += 1

    def _ignore(self) -> None:
        with self._cond:
            self.ignored += 1

    # called from the owning thread ----------------------------------------------
    def _pop(self):
        item = self._items.popleft()
        self.nbytes -= _size_of(item)
        return item

    def poll(self):
        """Return the oldest item, or ``None`` if empty (never blocks)."""
        with self._cond:
            return self._pop() if self._items else None

    def get(self, timeout: float | None = None):
        """Return the oldest item, waiting up to `timeout` s (None: forever); ``None`` on timeout."""
        with self._cond:
            if not self._cond.wait_for(lambda: self._items, timeout):
                return None
            return self._pop()

    def drain(self, max_items: int | None = None) -> list:
        """Return (and remove) up to `max_items` queued items, oldest first."""
        with self._cond:
            n = len(self._items) if max_items is None else min(max_items, len(self._items))
            return [self._pop() for _ in range(n)]

    def __len__(self) -> int:
        return len(self._items)

    def close(self) -> None:
        """Undeclare the subscriber feeding this inbox (idempotent)."""
        sub, self._subscriber = self._subscriber, None
        if sub is not None:
            try:
                sub.undeclare()
            except zenoh.ZError:
                pass  # session already closed


class KeySetInbox(Inbox):
    """An :class:`Inbox` fed by a set of key expressions that can change while it is in use
    (:meth:`follow`): one subscriber per key expression, all into this one queue.

    A key followed with ``history`` > 0 is subscribed with zenoh's advanced subscriber: on
    declaration it also receives the last ``history`` samples of each publisher of the key
    that keeps a cache (:meth:`Peer.publisher` with ``cache``), in order, before the live
    ones. A receiver that starts listening to a key late still gets what was just
    published on it (a samples' overlap with the live stream is possible: the owner keys
    what it keeps by the message's own stamp).
    """

    def __init__(self, declare, maxlen: int = DEFAULT_INBOX_SIZE,
                 wakeup: threading.Event | None = None, max_bytes: int = DEFAULT_INBOX_BYTES,
                 max_payload: int = MAX_PAYLOAD_BYTES):
        super().__init__(maxlen, wakeup, max_bytes=max_bytes, max_payload=max_payload)
        self._declare = declare                 # (keyexpr, history) -> subscriber
        self._subscribers: dict = {}            # keyexpr -> (history, subscriber)

    @property
    def keys(self) -> dict:
        """``{key expression: history}`` currently subscribed."""
        return {k: h for k, (h, _) in self._subscribers.items()}

    def follow(self, wanted) -> tuple:
        """Subscribe to exactly ``wanted`` (an iterable of key expressions, or a mapping of
        key expression -> history); returns ``(added, removed)`` key expressions.

        New keys are declared first, then the keys no longer wanted are undeclared, so a
        key that stays is never interrupted. Items already queued stay queued."""
        wanted = dict(wanted) if isinstance(wanted, dict) else {k: 0 for k in wanted}
        for k, h in wanted.items():
            _check_bound("history", h, 0)
        added = [k for k, h in wanted.items()
                 if k not in self._subscribers or self._subscribers[k][0] != h]
        removed = [k for k in self._subscribers if k not in wanted]
        for k in added:
            old = self._subscribers.pop(k, None)
            self._subscribers[k] = (wanted[k], self._declare(k, wanted[k]))
            if old is not None:
                _undeclare(old[1])
        for k in removed:
            _undeclare(self._subscribers.pop(k)[1])
        return tuple(added), tuple(removed)

    def close(self) -> None:
        """Undeclare every subscriber feeding this inbox (idempotent)."""
        subs, self._subscribers = self._subscribers, {}
        for _, sub in subs.values():
            _undeclare(sub)


def _undeclare(sub) -> None:
    try:
        sub.undeclare()
    except zenoh.ZError:
        pass  # session already closed


#: How long :meth:`Peer.claim` keeps asking whether another session holds its id after
#: its first link is up (the links gossip finds come up meanwhile); how long it waits for
#: a first link; the longest it waits for another holder to let go.
CLAIM_SETTLE_S = 0.3
CLAIM_LINK_S = 1.0
CLAIM_WAIT_MAX_S = 10.0
#: Sessions a :class:`LivelinessWatch` tracks for one ``(role, id)``: a process declaring
#: tokens under made-up session chunks cannot grow it beyond this.
MAX_SESSIONS_PER_ID = 16


class LivelinessWatch(Inbox):
    """Inbox of :class:`LivelinessEvent` that also tracks who is alive.

    :meth:`alive` and :meth:`wait_until` read the tracked set and do not
    consume events, so a thread can wait for peers while another (or the
    same, later) drains the events.
    """

    def __init__(self, prefix: str, maxlen: int = DEFAULT_INBOX_SIZE, wakeup: threading.Event | None = None):
        super().__init__(maxlen, wakeup)
        self.prefix = prefix
        self._tokens: dict[tuple[str, str], frozenset] = {}   # (role, id) -> live sessions

    def _on_sample(self, sample) -> None:
        try:
            key = str(sample.key_expr)
            try:
                role, id_, session = keys.parse_token_key(self.prefix, key)
            except keys.InvalidKey:
                self._ignore()
                return
            alive = sample.kind == zenoh.SampleKind.PUT
            with self._cond:
                sessions = self._tokens.get((role, id_), frozenset())
                if alive and session not in sessions and len(sessions) >= MAX_SESSIONS_PER_ID:
                    self.ignored += 1       # made-up sessions for one id: bounded
                    return
                sessions = sessions | {session} if alive else sessions - {session}
                if sessions:
                    self._tokens[(role, id_)] = sessions
                else:
                    self._tokens.pop((role, id_), None)
            self._push(LivelinessEvent(role, id_, alive, key, time.monotonic(), session,
                                       sessions))
        except Exception:  # never raise into zenoh
            self._ignore()

    def alive(self) -> frozenset:
        """Return the set of ``(role, id)`` currently alive (ids are str)."""
        with self._cond:
            return frozenset(self._tokens)

    def sessions(self, role: str, id) -> frozenset:
        """The zids of the sessions holding a token for ``(role, id)`` now."""
        with self._cond:
            return self._tokens.get((role, str(id)), frozenset())

    def wait_until(self, predicate: Callable[[frozenset], bool], timeout: float) -> bool:
        """Wait until ``predicate(alive_set)`` is true; return False on timeout."""
        deadline = time.monotonic() + timeout
        with self._cond:
            while not predicate(frozenset(self._tokens)):
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    return False
                self._cond.wait(min(remaining, 0.25))
        return True


def _direct(callback):
    """`callback` run in zenoh's receive thread (``indirect=False``).

    A plain Python callable is run by zenoh-python on a thread of its own, fed by a queue
    of 256 samples: every message then costs a thread hop, and a burst waits in that queue
    whatever the inbox's byte bound (a flood of 75 kB control payloads held about 19 MB
    there). Run directly, the callback (a copy into a bounded inbox) holds the receive
    thread, so the sender meets TCP's back-pressure instead.
    """
    return zenoh.handlers.Callback(callback, indirect=False)


class Peer:
    """A process on the zenoh mesh.

    Opens one zenoh session in peer mode and declares the liveliness token
    ``<alive_prefix>/<role>/<id>/<zid>`` (the session's own zid). Closing (context manager exit,
    :meth:`close`, or interpreter exit) undeclares everything; it is
    idempotent.

    Parameters
    ----------
    net : NetConfig
    role : str
        ``"agent"``, ``"world"``, ``"monitor"``, ... (a key chunk).
    id : int or str
        Process id within its role.
    alive_prefix : str
        Key expression the liveliness tokens of the mesh live under, the caller's
        (socmon's: :func:`agent.protocol.topics.alive_prefix`, or open the peer with
        :func:`agent.protocol.topics.open_peer`).

    Raises
    ------
    SessionError
        (a ``zenoh.ZError``) If the session cannot be opened (e.g. the listen port is
        taken, or a secured process reached none of its connect endpoints in time).
        Unreachable ``connect`` endpoints are not an error: zenoh keeps
        retrying them, so processes may start in any order.

    Examples
    --------
    >>> with Peer(NetConfig(run="demo"), "agent", 3, alive_prefix="app/demo/alive") as peer:  # doctest: +SKIP
    ...     inbox = peer.subscribe("app/demo/est/*")
    ...     peer.put("app/demo/est/3", payload)
    ...     item = inbox.get(timeout=1.0)
    """

    def __init__(self, net: NetConfig, role: str, id, *, alive_prefix: str):
        if not isinstance(net, NetConfig):
            raise TypeError(f"net: expected NetConfig, got {type(net).__name__}")
        self.net = net
        self.run = net.run
        self.role = role
        self.id = id
        self.alive_prefix = alive_prefix
        keys.token_key(alive_prefix, role, id, "0")  # validates role and id before opening
        self._pid = os.getpid()
        self._lock = threading.Lock()
        self._publishers: dict[str, tuple[zenoh.Publisher, bool]] = {}
        self._inboxes: list[Inbox] = []
        self._watch: LivelinessWatch | None = None
        self._closed = False
        self._activity = threading.Event()
        try:
            self._session = zenoh.open(build_zenoh_config(net))
        except zenoh.ZError as exc:
            raise SessionError(net, zenoh_message(exc)) from None
        # zenoh's links linger 10 s on close: a peer's host cut off would put this
        # process's receive threads to sleep until it returns (see linger.py)
        self._linger = LingerGuard()
        try:
            self._token = self._session.liveliness().declare_token(
                keys.token_key(alive_prefix, role, id, str(self._session.zid())))
        except BaseException:
            self._linger.stop()
            self._session.close()
            raise
        atexit.register(self.close)

    # -- lifecycle -------------------------------------------------------------

    def __enter__(self) -> Peer:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    @property
    def closed(self) -> bool:
        return self._closed

    def _check_usable(self) -> None:
        if os.getpid() != self._pid:
            raise RuntimeError("Peer used in a forked child; start processes with subprocess or 'spawn'")
        if self._closed:
            raise RuntimeError("Peer is closed")

    def close(self) -> None:
        """Undeclare the token, subscribers and publishers and close the session.

        Idempotent and never raises a zenoh error (a failed session close is
        logged). May take up to ~10 s if a peer is hung at that moment.
        """
        with self._lock:
            if self._closed:
                return
            self._closed = True
        atexit.unregister(self.close)
        if os.getpid() != self._pid:
            return  # forked child: the session belongs to the parent
        for inbox in self._inboxes:
            inbox.close()
        for pub, _ in self._publishers.values():
            try:
                pub.undeclare()
            except zenoh.ZError:
                pass
        try:
            self._token.undeclare()
        except zenoh.ZError:
            pass
        self._linger.stop()
        try:
            self._session.close()
        except zenoh.ZError as exc:
            # zenoh gives up after ~10 s when a link is stuck (e.g. a SIGSTOPped
            # peer mid-handshake; see eclipse-zenoh/zenoh#2675). The session's
            # entities are already undeclared; the rest goes with the process.
            _log.warning("zenoh session close of %s/%s: %s", self.role, self.id, exc)

    # -- info ----------------------------------------------------------------------

    @property
    def session(self) -> zenoh.Session:
        """The underlying zenoh session (for advanced use)."""
        self._check_usable()
        return self._session

    def zid(self) -> str:
        """Return this session's zenoh id."""
        return str(self.session.zid())

    def other_holders(self, timeout: float = 0.5) -> frozenset:
        """The zids of the sessions other than this one that hold a liveliness token for
        this peer's ``(role, id)`` now, as the peers it reaches answer a liveliness query
        within ``timeout`` seconds."""
        pattern = keys.token_key(self.alive_prefix, self.role, self.id, "x")[:-1] + "*"
        own, out = self.zid(), set()
        for reply in self.session.liveliness().get(pattern, timeout=timeout):
            sample = reply.ok
            if sample is None:
                continue
            try:
                _, _, session = keys.parse_token_key(self.alive_prefix, str(sample.key_expr))
            except keys.InvalidKey:
                continue
            if session != own:
                out.add(session)
        return frozenset(out)

    def claim(self, wait_s: float | None = None, say=None, stop=lambda: False) -> None:
        """Make sure this process is the only one of its ``(role, id)``: wait up to
        ``wait_s`` (default two leases and a second, at most :data:`CLAIM_WAIT_MAX_S`)
        for any other session holding its token to let go (a process just killed holds it
        until its lease expires), then raise :class:`IdInUse` naming it. ``say(text)`` is
        told once that it waits; ``stop()`` true ends the wait (no refusal).

        Best effort: a peer answers for its own tokens only, so a holder is found when
        this session links to it within :data:`CLAIM_SETTLE_S` of its first link: in a
        mesh that gossips (by hand, as docs/runtime.md runs it) or through a router; in
        ``socmon up``'s mesh, where each process links only to those started before it,
        not always (``up`` starts each id once)."""
        if wait_s is None:
            wait_s = min(2 * self.net.lease_ms / 1000.0 + 1.0, CLAIM_WAIT_MAX_S)
        # the peers answer for their own tokens only: ask once a link is up (a peer found
        # by gossip is linked shortly after the session opens), and again for a moment
        # after; a process that is first of its run has nobody to ask
        first_link = time.monotonic() + min(wait_s, CLAIM_LINK_S)
        while not (self.connected_peers() or list(self.session.info.routers_zid())) \
                and time.monotonic() < first_link and not stop():
            time.sleep(0.05)
        others, settled = self.other_holders(), time.monotonic() + CLAIM_SETTLE_S
        while not others and time.monotonic() < settled and not stop():
            time.sleep(0.1)
            others = self.other_holders()
        if not others or stop():
            return
        if say is not None:
            say(f"another session ({', '.join(sorted(others))}) holds the token of "
                f"{self.role} {self.id}; waiting up to {wait_s:g} s for it to go (a process "
                "just stopped holds it for its lease)")
        deadline = time.monotonic() + wait_s
        while others and time.monotonic() < deadline and not stop():
            time.sleep(0.1)
            others = self.other_holders()
        if others and not stop():      # stopped meanwhile: the caller stops, no refusal
            raise IdInUse(self, others)

    def connected_peers(self) -> list[str]:
        """Return the zenoh ids of directly connected peers."""
        return [str(z) for z in self.session.info.peers_zid()]

    # -- publish -----------------------------------------------------------------

    def publisher(self, key: str, *, block: bool | None = None, express: bool = False,
                  priority: str | None = None, cache: int = 0) -> zenoh.Publisher:
        """Return the publisher of `key`, declaring it on first use.

        Parameters
        ----------
        key : str
        block : bool, optional
            Congestion control, fixed when the publisher is declared:
            ``False`` (default; zenoh's ``DROP``) lets zenoh drop the message
            when the outgoing queue stays full, which suits periodic
            estimates; ``True`` (``BLOCK``) makes ``put`` wait instead, for
            messages that must not be lost (control, impairments). ``None``
            reuses the existing publisher whatever its mode.
        express : bool
            Send each message at once instead of batching it with others (zenoh's
            ``express``): lower latency for small periodic messages (estimates, sensor
            readings). Used when the publisher is declared.
        priority : str, optional
            A :class:`zenoh.Priority` name (``"REAL_TIME"``, ``"INTERACTIVE_HIGH"``,
            ``"DATA_HIGH"``, ...); default zenoh's ``DATA``. Used when the publisher is
            declared.
        cache : int
            Keep the last ``cache`` samples for subscribers that ask for history
            (zenoh's advanced publisher; :meth:`subscribe_keys` with ``history``): a
            receiver that subscribes late still gets them. Used when the publisher is
            declared; 0 (default): a plain publisher.

        Raises
        ------
        ValueError
            If `block` contradicts the mode of the already declared publisher, or
            `priority` is not a zenoh priority.
        """
        self._check_usable()
        entry = self._publishers.get(key)
        if entry is None:
            mode = bool(block)
            cc = zenoh.CongestionControl.BLOCK if mode else zenoh.CongestionControl.DROP
            options = {"congestion_control": cc}
            if express:
                options["express"] = True
            if priority is not None:
                if priority not in _PRIORITIES:
                    raise ValueError(f"priority: {priority!r} is not one of {_PRIORITIES}")
                options["priority"] = getattr(zenoh.Priority, priority)
            _check_bound("cache", cache, 0)
            if cache:
                pub = zenoh.ext.declare_advanced_publisher(
                    self._session, key, cache=zenoh.ext.CacheConfig(max_samples=cache),
                    **options)
            else:
                pub = self._session.declare_publisher(key, **options)
            entry = (pub, mode)
            self._publishers[key] = entry
        elif block is not None and block != entry[1]:
            raise ValueError(f"block: publisher of {key!r} already declared with block={entry[1]}")
        return entry[0]

    def put(self, key: str, payload: bytes) -> None:
        """Publish `payload` on `key` through its (cached) publisher."""
        self.publisher(key).put(payload)

    # -- subscribe ---------------------------------------------------------------

    def subscribe(self, keyexpr: str, maxlen: int = DEFAULT_INBOX_SIZE, *,
                  include_local: bool = True, max_bytes: int = DEFAULT_INBOX_BYTES,
                  max_payload: int = MAX_PAYLOAD_BYTES) -> Inbox:
        """Subscribe to `keyexpr`; return an :class:`Inbox` of :class:`Received`.

        Parameters
        ----------
        keyexpr : str
            Key or pattern (``*`` one chunk, ``**`` any number).
        maxlen : int
            Inbox capacity in items; on overflow the oldest item is dropped and counted.
        include_local : bool
            If False, publications of this same session are not delivered
            (by default zenoh delivers them, e.g. an agent subscribed to
            ``est/*`` receives its own estimates).
        max_bytes : int
            Inbox capacity in payload bytes (at least `max_payload`); on overflow the
            oldest items are dropped and counted.
        max_payload : int
            Larger payloads are refused before being copied out of zenoh (counted in
            ``inbox.oversized``); default the codec's 1 MiB limit.

        DELETE samples are ignored (counted in ``inbox.ignored``).
        """
        self._check_usable()
        inbox = Inbox(maxlen, self._activity, max_bytes=max_bytes, max_payload=max_payload)
        origin = zenoh.Locality.ANY if include_local else zenoh.Locality.REMOTE
        inbox._subscriber = self._session.declare_subscriber(keyexpr, _direct(_feeder(inbox)),
                                                             allowed_origin=origin)
        self._inboxes.append(inbox)
        return inbox

    def subscribe_keys(self, wanted, maxlen: int = DEFAULT_INBOX_SIZE, *,
                       include_local: bool = True, max_bytes: int = DEFAULT_INBOX_BYTES,
                       max_payload: int = MAX_PAYLOAD_BYTES) -> KeySetInbox:
        """Subscribe to a set of key expressions that may change later; return a
        :class:`KeySetInbox` (its :meth:`~KeySetInbox.follow` changes the set).

        ``wanted``: key expressions, or a mapping key expression -> history (the samples
        of each caching publisher received on declaration, see :class:`KeySetInbox`).
        The other parameters are those of :meth:`subscribe`, for every key.
        """
        self._check_usable()
        origin = zenoh.Locality.ANY if include_local else zenoh.Locality.REMOTE
        inbox = None

        def declare(keyexpr, history):
            self._check_usable()
            handler = _direct(_feeder(inbox))
            if not history:
                return self._session.declare_subscriber(keyexpr, handler,
                                                        allowed_origin=origin)
            return zenoh.ext.declare_advanced_subscriber(
                self._session, keyexpr, handler, allowed_origin=origin,
                history=zenoh.ext.HistoryConfig(max_samples=history))

        inbox = KeySetInbox(declare, maxlen, self._activity, max_bytes=max_bytes,
                            max_payload=max_payload)
        inbox.follow(wanted)
        self._inboxes.append(inbox)
        return inbox

    def watch_liveliness(self, maxlen: int = DEFAULT_INBOX_SIZE) -> LivelinessWatch:
        """Watch ``<alive_prefix>/**`` (with history: peers already alive are reported).

        Returns a :class:`LivelinessWatch`; this peer's own token is included.
        """
        self._check_usable()
        watch = LivelinessWatch(self.alive_prefix, maxlen, self._activity)
        watch._subscriber = self._session.liveliness().declare_subscriber(
            keys.token_pattern(self.alive_prefix), _direct(watch._on_sample), history=True)
        self._inboxes.append(watch)
        return watch

    def wait(self, timeout: float | None = None) -> bool:
        """Wait until any inbox of this peer received something since the last call.

        Returns False on timeout. Consumes nothing: drain the inboxes after
        it. An item that arrives while you drain makes the next call return
        at once (a spurious wake-up, never a lost one).

        Examples
        --------
        >>> while running:                                   # doctest: +SKIP
        ...     peer.wait(timeout=step_left)
        ...     for item in est_inbox.drain(): ...
        ...     for event in watch.drain(): ...
        """
        fired = self._activity.wait(timeout)
        self._activity.clear()
        return fired

    def wait_for_peers(self, predicate: Callable[[frozenset], bool], timeout: float) -> bool:
        """Wait until ``predicate(alive)`` holds, `alive` being a set of ``(role, id)`` str pairs.

        Uses (and creates on first call) a liveliness watch owned by the peer.
        Returns False on timeout.

        Examples
        --------
        >>> peer.wait_for_peers(lambda alive: {("agent", "0"), ("agent", "1")} <= alive, 10.0)  # doctest: +SKIP
        """
        if self._watch is None:
            self._watch = self.watch_liveliness()
        return self._watch.wait_until(predicate, timeout)

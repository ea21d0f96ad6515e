"""A zenoh router for runs larger than a peer mesh.

In peer mode (the default) every process of a run links to every other: N processes hold
N(N-1)/2 links and each put is sent once per subscriber. In client mode a process holds one
link, to a router, and the router forwards each sample to the subscribers: N links, one
more hop. :class:`Router` opens a router session in this process (the zenoh Python binding
routes like ``zenohd``; ``zenohd`` itself is neither on PyPI nor in Debian, see
docs/transport.md for production), :func:`serve_router` runs one until SIGTERM or SIGINT.

Several routers connect to each other with ``connect`` (each router lists another's
endpoint); a client lists several routers in its ``connect`` and uses the first that
answers.

The router knows nothing of runs or estimation: it routes every key. It is not available
with ``keys`` (the access control of a secured run names the process at the other end of
each link; see :class:`broker_free_net.config.NetConfig`).

Examples
--------
>>> net = NetConfig(listen=("tcp/127.0.0.1:0",))
>>> with Router(net) as router:                        # doctest: +SKIP
...     router.endpoints()
['tcp/127.0.0.1:40123']
"""

from __future__ import annotations

import json
import signal
import threading

import zenoh

from .config import InvalidNetConfig, NetConfig, build_zenoh_config
from .linger import LingerGuard

__all__ = ["DEFAULT_ROUTER_LISTEN", "Router", "router_config", "serve_router"]

#: Where ``socmon router`` listens by default (zenoh's usual port, loopback only).
DEFAULT_ROUTER_LISTEN = ("tcp/127.0.0.1:7447",)


def router_config(net: NetConfig) -> zenoh.Config:
    """The ``zenoh.Config`` of a router: :func:`build_zenoh_config` of `net` in router mode.

    The router's admin space is enabled read-only, so that it can report the endpoints it
    really listens on (port 0 resolved) and the sessions attached to it.

    Raises
    ------
    InvalidNetConfig
        `net` has keys (not supported) or asks for client mode.
    """
    if not isinstance(net, NetConfig):
        raise TypeError(f"net: expected NetConfig, got {type(net).__name__}")
    if net.keys is not None:
        raise InvalidNetConfig("keys", "a router cannot run with keys: the access control of "
                                       "a secured run names the process at the other end of "
                                       "a link, which a router would hide (use the peer mesh)")
    if net.mode == "client":
        raise InvalidNetConfig("mode", "a router is not a client")
    conf = build_zenoh_config(net)
    conf.insert_json5("mode", json.dumps("router"))
    conf.insert_json5("adminspace", json.dumps({"enabled": True,
                                                "permissions": {"read": True, "write": False}}))
    return conf


class Router:
    """A zenoh router session in this process; a context manager.

    Parameters
    ----------
    net : NetConfig
        ``listen`` (where clients and other routers connect), ``connect`` (other routers),
        ``lease_ms``, ``multicast``, ``zenoh_config``. ``run`` is not used: a router
        routes every run.

    Raises
    ------
    InvalidNetConfig
        See :func:`router_config`.
    zenoh.ZError
        The session cannot be opened (e.g. the listen port is taken).
    """

    def __init__(self, net: NetConfig):
        self.net = net
        self._session = zenoh.open(router_config(net))
        self._closed = False
        self._linger = LingerGuard()   # a cut-off client must not stall the router's rx

    def __enter__(self) -> Router:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def zid(self) -> str:
        """The router's zenoh id."""
        return str(self._session.info.zid())

    def _admin(self, timeout: float = 2.0) -> dict:
        for reply in self._session.get(f"@/{self.zid()}/router", timeout=timeout):
            if reply.ok is not None:
                return json.loads(reply.ok.payload.to_string())
        return {}

    def endpoints(self) -> list[str]:
        """The endpoints the router listens on, with ports chosen by the OS resolved."""
        found = self._admin().get("locators")
        return list(found) if found else list(self.net.listen)

    def sessions(self) -> int:
        """How many sessions (clients, peers, other routers) are attached now."""
        return len(self._admin().get("sessions") or [])

    def close(self) -> None:
        """Close the session (idempotent)."""
        if self._closed:
            return
        self._closed = True
        self._linger.stop()
        try:
            self._session.close()
        except zenoh.ZError:
            pass


def serve_router(net: NetConfig, on_ready=None, stop: threading.Event | None = None) -> None:
    """Run a :class:`Router` until SIGTERM, SIGINT or `stop` is set.

    Parameters
    ----------
    net : NetConfig
    on_ready : callable or None
        Called with the open :class:`Router` once it listens (e.g. to print its endpoints).
    stop : threading.Event or None
        Set it to stop the router from another thread. From the main thread SIGTERM and
        SIGINT set it too (the previous handlers are restored on return).
    """
    stop = stop if stop is not None else threading.Event()
    old = {}
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGTERM, signal.SIGINT):
            old[sig] = signal.signal(sig, lambda *_: stop.set())
    try:
        with Router(net) as router:
            if on_ready is not None:
                on_ready(router)
            while not stop.wait(0.5):
                pass
    finally:
        for sig, handler in old.items():
            signal.signal(sig, handler)

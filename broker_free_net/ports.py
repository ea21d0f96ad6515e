"""Ports to listen on for processes started together on one host.

A port the OS picks with ``bind(port=0)`` comes from its *ephemeral* range, the same range
it draws the source ports of outgoing connections from. Between the moment a launcher
learns such a port and the moment its child binds it, any zenoh session of the run that
connects somewhere may take it as a source port, and the child dies with "Address already in
use". :func:`listen_port` therefore picks ports *below* the ephemeral range, where the OS
never assigns a source port, checks that each is free, and never hands out the same one
twice in one process.

Examples
--------
>>> p = listen_port()
>>> lo, _ = ephemeral_range()
>>> LOWEST_PORT <= p < lo or p > ephemeral_range()[1]
True
>>> listen_port() != p
True
"""

from __future__ import annotations

import random
import socket

__all__ = ["LOWEST_PORT", "ephemeral_range", "listen_port"]

#: Ports below this are left to services (databases, brokers, ...).
LOWEST_PORT = 20000
_DEFAULT_EPHEMERAL = (32768, 60999)
_handed_out: set = set()
_draw = random.SystemRandom()


def ephemeral_range() -> tuple[int, int]:
    """The OS's range of source ports for outgoing connections (Linux; else the default)."""
    try:
        with open("/proc/sys/net/ipv4/ip_local_port_range") as f:
            lo, hi = (int(v) for v in f.read().split())
        return lo, hi
    except (OSError, ValueError):
        return _DEFAULT_EPHEMERAL


def _is_free(host: str, port: int) -> bool:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        try:
            s.bind((host, port))
        except OSError:
            return False
    return True


def listen_port(host: str = "127.0.0.1", attempts: int = 200) -> int:
    """A TCP port on `host` that is free now and outside the ephemeral range.

    Raises
    ------
    RuntimeError
        If no free port was found in `attempts` draws.
    """
    lo, hi = ephemeral_range()
    pool = [(LOWEST_PORT, lo)] if lo - LOWEST_PORT >= 1000 else []
    if hi < 65535:
        pool.append((hi + 1, 65536))
    if not pool:               # the whole range is ephemeral: any unprivileged port, checked
        pool = [(1024, 65536)]
    for _ in range(attempts):
        a, b = _draw.choice(pool)
        port = _draw.randrange(a, b)
        if port in _handed_out or not _is_free(host, port):
            continue
        _handed_out.add(port)
        return port
    raise RuntimeError(f"no free TCP port on {host} outside the ephemeral range "
                       f"{lo}-{hi} after {attempts} draws")

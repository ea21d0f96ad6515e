"""Keep zenoh's TCP links from blocking a runtime thread when a peer's host is cut off.

zenoh 1.10 sets ``SO_LINGER`` to 10 s on every TCP (and TLS) link it opens. On Linux a
``close()`` of such a socket waits, in the calling thread, until the data still queued
for the peer is acknowledged or the 10 s pass, whether or not the socket is non-blocking.
When a peer's host is cut off (a cable pulled, a link brought down), every process that
talked to it has unacknowledged data queued; once the 1 s lease expires zenoh closes the
link from one of its two receive threads, which then sleeps in ``close()`` until the host
comes back. Measured on the namespace testbed (a kernel stack of ``sk_stream_wait_close``
in ``rx-0`` and ``rx-1`` of the monitor, the world and the agents while agent 2's link
was down): with both receive threads of a process asleep it hears nothing, and the
monitor convicted healthy agents. zenoh tracks this upstream (eclipse-zenoh/zenoh#1101,
#2350) and has no setting for it.

:class:`LingerGuard` turns lingering off on the process's own TCP sockets, as the
operating system's default is: ``close()`` returns at once and the kernel still sends
what is queued (a graceful close, as without ``SO_LINGER``). It scans ``/proc/self/fd``
for sockets it has not seen, so a link zenoh opens later (a peer that joins or
reconnects) is covered within one period. Elsewhere than Linux it does nothing.

>>> import socket, struct
>>> s = socket.socket()
>>> s.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 10))
>>> clear_linger(set()) >= 1
True
>>> struct.unpack("ii", s.getsockopt(socket.SOL_SOCKET, socket.SO_LINGER, 8))[0]
0
>>> s.close()
"""

from __future__ import annotations

import logging
import os
import socket
import struct
import threading

__all__ = ["LINGER_SCAN_S", "LingerGuard", "clear_linger"]

#: How often the guard looks for new sockets (seconds). A link opened to a host that is
#: cut off less than this after the link opened may still linger once.
LINGER_SCAN_S = 0.2
_FD_DIR = "/proc/self/fd"
_LINGER_OFF = struct.pack("ii", 0, 0)
_log = logging.getLogger(__name__)


def _socket_inodes() -> dict[int, str]:
    """fd -> ``socket:[inode]`` of this process's open sockets (empty if not Linux)."""
    out = {}
    try:
        names = os.listdir(_FD_DIR)
    except OSError:
        return out
    for name in names:
        try:
            target = os.readlink(f"{_FD_DIR}/{name}")
        except OSError:               # closed since the listing
            continue
        if target.startswith("socket:"):
            out[int(name)] = target
    return out


def clear_linger(seen: set[str]) -> int:
    """Turn ``SO_LINGER`` off on this process's TCP sockets not in `seen`.

    `seen` holds the ``socket:[inode]`` names already handled; it is updated in place
    (new sockets added, closed ones removed). Returns how many sockets had lingering on.
    """
    current = _socket_inodes()
    seen.intersection_update(current.values())
    cleared = 0
    for fd, inode in current.items():
        if inode in seen:
            continue
        try:
            dup = os.dup(fd)
        except OSError:
            continue
        try:
            sock = socket.socket(fileno=dup)          # owns dup, not fd
        except OSError:                               # fd reused by a non-socket
            os.close(dup)
            continue
        try:
            inode = os.readlink(f"{_FD_DIR}/{dup}")   # what dup is (fd may be reused)
            if inode in seen:
                continue
            seen.add(inode)
            if sock.family not in (socket.AF_INET, socket.AF_INET6) \
                    or sock.type != socket.SOCK_STREAM:
                continue
            onoff, _ = struct.unpack("ii", sock.getsockopt(socket.SOL_SOCKET,
                                                           socket.SO_LINGER, 8))
            if onoff:
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, _LINGER_OFF)
                cleared += 1
        except OSError:
            continue
        finally:
            sock.close()
    return cleared


class LingerGuard:
    """A daemon thread that runs :func:`clear_linger` every `period` seconds until stopped.

    >>> guard = LingerGuard(period=0.05)
    >>> guard.stop()
    """

    def __init__(self, period: float = LINGER_SCAN_S):
        self.period = period
        self.cleared = 0
        self._seen: set[str] = set()
        self._stop = threading.Event()
        self.scan()
        self._thread = threading.Thread(target=self._run, name="linger-guard", daemon=True)
        self._thread.start()

    def scan(self) -> int:
        """One pass now; returns the sockets changed."""
        n = clear_linger(self._seen)
        self.cleared += n
        return n

    def _run(self) -> None:
        while not self._stop.wait(self.period):
            try:
                self.scan()
            except Exception as exc:     # never take the process down
                _log.warning("linger guard: %s", exc)

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not threading.current_thread():
            self._thread.join(timeout=5.0)

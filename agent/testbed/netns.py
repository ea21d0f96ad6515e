"""A testbed of network namespaces: each process of a run on its own "host".

A :class:`Testbed` makes one network namespace per host and one *switch* namespace that
holds a Linux bridge; every host is wired to the switch by a veth pair (``eth0`` inside
the host, ``p-<host>`` on the bridge) and gets an address of :data:`SUBNET` on ``eth0``.
Hosts reach each other only through the bridge, over real IP links, as separate machines
on one switch would. Each host knows every other host's hardware address from the start
(permanent neighbour entries): the kernel's ARP table is one for all namespaces, at most
``gc_thresh3`` (1,024 by default) learned entries, and a mesh of 35 hosts needs 1,190;
past it a host's new neighbours were never resolved ("neighbor table overflow") and its
connections stayed in SYN-SENT, so one agent of a 32-agent mesh heard nobody. Permanent
entries are not counted against that limit (Linux 4.20 and later; before, a testbed that
large fails to be made, with the `ip` command's error). Nothing is added to the namespace the testbed
was made from: the veth pairs are created inside the switch namespace and their host ends
moved straight into the hosts, and every address lives inside a namespace the testbed
made. Testbeds made side by side do not collide (their namespaces are disjoint, so the
same subnet serves all); only the namespace names are global, so each testbed takes a
unique ``prefix``.

A link brought down (:meth:`Testbed.set_link`) is the host's cable pulled at the switch:
the bridge port goes down, the host's ``eth0`` loses its carrier, and packets in both
directions are lost until the port comes back; TCP connections time out or recover by
themselves, as on real machines. :meth:`Testbed.close` deletes every namespace (which
removes the bridge and the veth pairs with them); :func:`remove_testbed` does the same by
prefix for a testbed whose owner died.

Everything here needs root (``CAP_SYS_ADMIN``) and iproute2; :func:`unavailable_reason`
says in one line why a testbed cannot be made on this machine, or returns None.

Examples
--------
>>> host_names(3)
['recorder', 'world', 'agent-1', 'agent-2', 'agent-3', 'monitor']
>>> host_of("monitor-2"), host_of("monitor-1.restart-1")
('monitor', 'monitor')
"""

from __future__ import annotations

import contextlib
import ctypes
import ipaddress
import os
import re
import shutil
import subprocess

__all__ = ["SUBNET", "Testbed", "TestbedError", "check_prefix", "default_prefix", "host_names",
           "host_of", "list_namespaces", "prefix_taken", "remove_testbed", "unavailable_reason"]

#: Addresses of the hosts (the switch has none): .1 for the first host, .2 for the next...
SUBNET = ipaddress.ip_network("10.200.0.0/24")
#: Namespace names are ``<prefix>-<host>``; a prefix is short and plain.
_PREFIX_RE = re.compile(r"^[a-z][a-z0-9]{0,11}$")
_CLONE_NEWNET = 0x40000000
_IP_TIMEOUT_S = 20.0


class TestbedError(RuntimeError):
    """A namespace, link or address could not be made or changed (names the command)."""

    __test__ = False          # not a pytest test class


def _ip_binary() -> str | None:
    return shutil.which("ip") or next(
        (p for p in ("/usr/sbin/ip", "/sbin/ip", "/usr/bin/ip") if os.access(p, os.X_OK)), None)


def _run(*argv: str, batch: str | None = None) -> None:
    """``ip *argv``; with ``batch``, ``ip *argv -batch -`` fed those command lines."""
    ip = _ip_binary()
    if ip is None:
        raise TestbedError("iproute2's `ip` command was not found")
    if batch is not None:
        argv = (*argv, "-batch", "-")
    try:
        done = subprocess.run([ip, *argv], capture_output=True, text=True, input=batch,
                              timeout=_IP_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        raise TestbedError(f"`ip {' '.join(argv)}` did not finish in {_IP_TIMEOUT_S:g} s") \
            from None
    if done.returncode != 0:
        raise TestbedError(f"`ip {' '.join(argv)}` failed: "
                           f"{(done.stderr or done.stdout).strip() or done.returncode}")


def host_names(M: int, router: bool = False) -> list:
    """The processes of a run with ``M`` agents (standbys included), one host each, in
    endpoint order: recorder, world, agents, monitor, and the zenoh router of a routed run
    (``router``) on a host of its own, as it would be on real machines.

    >>> host_names(1, router=True)
    ['recorder', 'world', 'agent-1', 'monitor', 'router']
    """
    return (["recorder", "world", *(f"agent-{a}" for a in range(1, M + 1)), "monitor"]
            + (["router"] if router else []))


def host_of(process: str) -> str:
    """The host a process runs on: every monitor (``monitor-2``, a restarted
    ``monitor-1.restart-1``) on the monitors' host."""
    return "monitor" if process.startswith("monitor") else process


def check_prefix(prefix: str) -> str:
    """``prefix`` if it is a valid namespace prefix, else ValueError naming what is wrong.

    >>> check_prefix("run7")
    'run7'
    """
    if not isinstance(prefix, str) or not _PREFIX_RE.match(prefix):
        raise ValueError(f"prefix: expected 1-12 lower-case letters and digits starting "
                         f"with a letter, got {prefix!r}")
    return prefix


def prefix_taken(prefix: str) -> str | None:
    """Why a testbed of ``prefix`` cannot be made now (namespaces of that prefix exist),
    or None."""
    if any(n.startswith(prefix + "-") for n in list_namespaces()):
        return (f"namespaces named {prefix}-* exist already (another run, or one that "
                "died: delete them with `ip netns delete NAME`)")
    return None


def default_prefix() -> str:
    """A prefix unique on this machine while this process lives (``sm<pid>``)."""
    return f"sm{os.getpid()}"


def _short(host: str) -> str:
    """The host's part of its names (bridge port names have at most 15 characters)."""
    for long, short in (("agent-", "a"), ("recorder", "rec"), ("monitor", "mon"),
                        ("router", "rtr")):
        host = host.replace(long, short)
    return host


def list_namespaces() -> list:
    """Names of the named network namespaces (``/run/netns``)."""
    try:
        return sorted(os.listdir("/run/netns"))
    except OSError:
        return []


def remove_testbed(prefix: str) -> list:
    """Delete every namespace named ``<prefix>-*``; return the names deleted."""
    gone = []
    for name in list_namespaces():
        if name.startswith(prefix + "-"):
            with contextlib.suppress(TestbedError):
                _run("netns", "delete", name)
                gone.append(name)
    return gone


def unavailable_reason() -> str | None:
    """Why a testbed cannot be made here (one line), or None when it can.

    Tries what a testbed does: makes a namespace and a veth pair inside it, then removes it.
    """
    if not hasattr(os, "geteuid") or os.geteuid() != 0:
        return "network namespaces need root (run as root, e.g. in CI or a container " \
               "with CAP_SYS_ADMIN and CAP_NET_ADMIN)"
    if _ip_binary() is None:
        return "iproute2's `ip` command was not found"
    probe = f"smprobe{os.getpid()}-x"
    try:
        _run("netns", "add", probe)
        _run("-n", probe, "link", "add", "p0", "type", "veth", "peer", "name", "p1")
    except TestbedError as exc:
        return f"cannot make a network namespace with a veth pair: {exc}"
    finally:
        with contextlib.suppress(TestbedError):
            _run("netns", "delete", probe)
    return None


class Testbed:
    """Hosts on one switch, each in its own network namespace; a context manager.

    Parameters
    ----------
    hosts : list of str
        Host names (letters, digits and ``-``), e.g. :func:`host_names`.
    prefix : str, optional
        Namespace names are ``<prefix>-<host>`` and ``<prefix>-switch``; lower-case letters
        and digits, at most 12. Default :func:`default_prefix`.

    Examples
    --------
    Needs root::

        with Testbed(["a", "b"], prefix="demo") as tb:
            tb.ip("b")                      # '10.200.0.2'
            tb.exec_prefix("a")             # ['ip', 'netns', 'exec', 'demo-a']
            tb.set_link("b", up=False)      # b is cut off
            tb.set_link("b", up=True)       # and back
    """

    __test__ = False

    def __init__(self, hosts, prefix: str | None = None):
        prefix = default_prefix() if prefix is None else check_prefix(prefix)
        hosts = list(hosts)
        if len(set(hosts)) != len(hosts):
            raise ValueError(f"hosts: names must be unique, got {hosts}")
        if len(hosts) > SUBNET.num_addresses - 2:
            raise ValueError(f"hosts: at most {SUBNET.num_addresses - 2}, got {len(hosts)}")
        for h in hosts:
            if not re.match(r"^[a-z][a-z0-9-]*$", h) or len("p-" + _short(h)) > 15:
                raise ValueError(f"hosts: {h!r} is not a short host name of letters, digits "
                                 f"and '-'")
        self.prefix = prefix
        self.hosts = hosts
        self.switch = f"{prefix}-switch"
        self._ips = {h: str(SUBNET.network_address + i + 1) for i, h in enumerate(hosts)}
        self._made = []
        self._up = {h: True for h in hosts}

    # -- names ---------------------------------------------------------------------------
    def namespace(self, host: str) -> str:
        """The network namespace of ``host``."""
        self._check(host)
        return f"{self.prefix}-{_short(host)}"

    def ip(self, host: str) -> str:
        """The address of ``host`` (on its ``eth0``)."""
        self._check(host)
        return self._ips[host]

    def mac(self, host: str) -> str:
        """The hardware address of ``host``'s ``eth0``: locally administered, its IPv4
        address in the last four bytes (``10.200.0.2`` -> ``02:00:0a:c8:00:02``)."""
        address = ipaddress.ip_address(self.ip(host)).packed
        return "02:00:" + ":".join(f"{b:02x}" for b in address)

    def port(self, host: str) -> str:
        """The bridge port (in the switch namespace) that ``host`` is wired to."""
        self._check(host)
        return f"p-{_short(host)}"

    def exec_prefix(self, host: str) -> list:
        """argv prefix that runs a command on ``host`` (``ip netns exec`` execs in place,
        so the command keeps the PID and process group it was started with)."""
        return [_ip_binary() or "ip", "netns", "exec", self.namespace(host)]

    def is_up(self, host: str) -> bool:
        self._check(host)
        return self._up[host]

    def _check(self, host):
        if host not in self._ips:
            raise KeyError(f"no host {host!r} in this testbed (hosts: {', '.join(self.hosts)})")

    # -- life ----------------------------------------------------------------------------
    def create(self) -> "Testbed":
        """Make the switch, the hosts, their links and addresses; undo all on any error."""
        taken = prefix_taken(self.prefix)
        if taken is not None:
            raise TestbedError(taken)
        try:
            self._add_ns(self.switch)
            sw = ("-n", self.switch)
            _run(*sw, "link", "add", "br0", "type", "bridge")
            _run(*sw, "link", "set", "br0", "up")
            for host in self.hosts:
                ns, port = self.namespace(host), self.port(host)
                self._add_ns(ns)
                _run("-n", ns, "link", "set", "lo", "up")
                _run(*sw, "link", "add", port, "type", "veth", "peer", "name", "eth0",
                     "address", self.mac(host), "netns", ns)
                _run(*sw, "link", "set", port, "master", "br0")
                _run(*sw, "link", "set", port, "up")
                _run("-n", ns, "addr", "add", f"{self.ip(host)}/{SUBNET.prefixlen}", "dev",
                     "eth0")
                _run("-n", ns, "link", "set", "eth0", "up")
            for host in self.hosts:
                _run("-n", self.namespace(host), batch="".join(
                    f"neigh replace {self.ip(h)} lladdr {self.mac(h)} dev eth0 nud permanent\n"
                    for h in self.hosts if h != host))
        except BaseException:
            self.close()
            raise
        return self

    def _add_ns(self, name):
        _run("netns", "add", name)
        self._made.append(name)

    def close(self) -> None:
        """Delete every namespace of the testbed (links and bridge go with them)."""
        errors = []
        while self._made:
            name = self._made.pop()
            try:
                _run("netns", "delete", name)
            except TestbedError as exc:
                errors.append(str(exc))
        if errors:
            raise TestbedError("; ".join(errors))

    def __enter__(self):
        return self.create()

    def __exit__(self, *exc):
        self.close()

    # -- faults ----------------------------------------------------------------------------
    def set_link(self, host: str, up: bool) -> None:
        """Bring ``host``'s bridge port down (its cable pulled) or up again."""
        _run("-n", self.switch, "link", "set", self.port(host), "up" if up else "down")
        self._up[host] = up

    # -- this process on a host ------------------------------------------------------------
    @contextlib.contextmanager
    def inside(self, host: str):
        """Run the calling thread on ``host`` until the block ends.

        A network namespace belongs to a thread: sockets the thread opens, and threads it
        starts (a zenoh session's runtime, when this is the first session of the process),
        are on ``host``. Sessions opened earlier in the process keep their threads where
        they were, so open the first session inside the block.
        """
        libc = ctypes.CDLL(None, use_errno=True)
        here = os.open("/proc/thread-self/ns/net", os.O_RDONLY)
        try:
            there = os.open(f"/run/netns/{self.namespace(host)}", os.O_RDONLY)
            try:
                if libc.setns(there, _CLONE_NEWNET) != 0:
                    err = ctypes.get_errno()
                    raise TestbedError(f"cannot enter {self.namespace(host)}: "
                                       f"{os.strerror(err)}")
            finally:
                os.close(there)
            try:
                yield self
            finally:
                if libc.setns(here, _CLONE_NEWNET) != 0:
                    raise TestbedError(f"cannot return from {self.namespace(host)}: "
                                       f"{os.strerror(ctypes.get_errno())}")
        finally:
            os.close(here)

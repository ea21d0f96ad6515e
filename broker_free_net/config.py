"""Session configuration: plain values -> ``zenoh.Config``.

The order of precedence is: zenoh defaults < the zenoh config file (json5, optional) <
the secure fragment of the process (``keys``, optional) < the values given to
:class:`NetConfig`. A field left unset (``None``) takes the file's value when the file sets
that key, else socmon's default; so a file with ``listen/endpoints`` or ``mode`` keeps them
unless a flag says otherwise. Keys socmon never sets pass through untouched (TLS, interfaces,
queue sizes, ...).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import stat
from dataclasses import dataclass, field
from pathlib import Path

import zenoh

__all__ = [
    "CLIENT_CONNECT_TIMEOUT_MS",
    "DEFAULT_LEASE_MS",
    "DEFAULT_LISTEN",
    "DEFAULT_SECURE_LISTEN",
    "MAX_CONFIG_BYTES",
    "MAX_MESSAGE_BYTES",
    "SOCMON_KEYS",
    "InvalidNetConfig",
    "NetConfig",
    "add_net_arguments",
    "build_zenoh_config",
    "net_config_from_args",
    "zenoh_message",
]

#: Default link lease. A peer that stops answering keep-alives (hung, killed,
#: cable pulled) is declared gone after at most this long, and its liveliness
#: tokens are withdrawn. zenoh's own default is 10 s.
DEFAULT_LEASE_MS = 1000
#: Keep-alive messages sent per lease period (zenoh ``transport/link/tx/keep_alive``).
KEEP_ALIVES_PER_LEASE = 4
#: Default listen endpoint: loopback, port chosen by the OS.
DEFAULT_LISTEN = ("tcp/127.0.0.1:0",)
#: Default listen endpoint of a secured process (``keys`` given).
DEFAULT_SECURE_LISTEN = ("tls/127.0.0.1:0",)
#: How long a client of one router keeps trying it before ``zenoh.open`` fails
#: (``connect/timeout_ms`` of a client with one connect endpoint, unless the config file
#: sets it). zenoh's client default is to try once, so a client started before its router
#: would die. A client of several routers keeps zenoh's default: while it waits, zenoh
#: 1.10 retries the first endpoint only (measured), so the others would never be tried.
CLIENT_CONNECT_TIMEOUT_MS = 10_000
#: How a lost link is tried again (``connect/retry``): every 250 ms, backing off to 500 ms.
CONNECT_RETRY = {"period_init_ms": 250, "period_max_ms": 500, "period_increase_factor": 2}
#: Largest message zenoh will reassemble (``transport/link/rx/max_message_size``).
#: zenoh's default is 1 GiB; socmon messages are a few hundred bytes.
MAX_MESSAGE_BYTES = 1 << 20
#: Largest zenoh config file read (a config is a few kB; certificates are files of their own).
MAX_CONFIG_BYTES = 1 << 20
#: The zenoh keys socmon sets, each with the NetConfig field or the fixed value it takes
#: when the config file does not set it.
SOCMON_KEYS = {
    "mode": "mode (default peer)",
    "listen/endpoints": "listen (--listen)",
    "connect/endpoints": "connect (--connect)",
    "scouting/multicast/enabled": "multicast (--multicast)",
    "transport/link/tx/lease": "lease_ms (--lease-ms)",
    "scouting/gossip/enabled": "true",
    "transport/link/tx/keep_alive": str(KEEP_ALIVES_PER_LEASE),
    "transport/link/rx/max_message_size": str(MAX_MESSAGE_BYTES),
    "connect/timeout_ms": f"{CLIENT_CONNECT_TIMEOUT_MS} (client of one router only)",
    "transport/shared_memory/enabled": "false",
    "connect/retry": "period 250 ms backing off to 500 ms",
}
_MODES = ("peer", "client")
#: The modes a socmon process may run in (a router is ``socmon router``, not a mode flag).
_PROCESS_MODES = _MODES
_RUN_RE = re.compile(r"^[A-Za-z0-9_.\-]+$")
# <protocol>/<address>[?<metadata>][#<config>]
_ENDPOINT_RE = re.compile(r"^[a-z][a-z0-9+\-]*/\S+$")
#: the port of an endpoint's address (before zenoh's ``?metadata`` and ``#config``)
_PORT_RE = re.compile(r":(\d+)(?:[?#].*)?$")


class InvalidNetConfig(ValueError):
    """A network configuration value is invalid.

    Attributes
    ----------
    field : str
        Name of the offending field (as in :class:`NetConfig`; ``zenoh_config`` and
        ``keys`` are also the names of their flags).
    """

    def __init__(self, field: str, message: str):
        self.field = field
        self.reason = message
        super().__init__(f"{field}: {message}")

    def as_flag(self) -> str:
        """The message as a command line says it, naming the flag.

        >>> InvalidNetConfig("zenoh_config", "no such file 'x'").as_flag()
        "--zenoh-config: no such file 'x'"
        """
        return f"--{self.field.replace('_', '-')}: {self.reason}"


def _check_endpoints(name: str, value) -> tuple[str, ...]:
    if isinstance(value, str):
        raise InvalidNetConfig(name, "expected a sequence of endpoints, got a single string")
    try:
        endpoints = tuple(value)
    except TypeError:
        raise InvalidNetConfig(name, f"expected a sequence of endpoints, got {type(value).__name__}") from None
    for ep in endpoints:
        if not isinstance(ep, str) or not _ENDPOINT_RE.match(ep):
            raise InvalidNetConfig(name, f"invalid endpoint {ep!r}, expected e.g. 'tcp/127.0.0.1:7447'")
        port = _PORT_RE.search(ep)
        if port is not None and int(port.group(1)) > 65535:
            raise InvalidNetConfig(name, f"invalid endpoint {ep!r}: port {int(port.group(1))} "
                                         "is not in 0..65535")
    return endpoints


def zenoh_message(exc: Exception) -> str:
    """One line out of a zenoh error (its json5 parser reports over several lines)."""
    text = re.sub(r"\s+at /\S+\.rs:\d+\.?", "", str(exc))  # locations in zenoh's sources
    serde = re.search(r'msg: "(.*?)", location: Some\(Location \{ line: (\d+), column: (\d+)', text)
    if serde:
        return f"line {serde.group(2)}, column {serde.group(3)}: {serde.group(1)}"
    where = re.search(r"-->\s*(\d+):(\d+)", text)
    what = re.search(r"=\s*(.+)", text)
    if where and what:
        return f"line {where.group(1)}, column {where.group(2)}: {what.group(1).strip()}"
    return " ".join(text.split())


def _flatten(tree: dict, prefix: str = ""):
    for k, v in tree.items():
        if isinstance(v, dict) and v:
            yield from _flatten(v, f"{prefix}{k}/")
        else:
            yield f"{prefix}{k}", v


_DEFAULTS: dict[str, object] = {}


def _default(key: str):
    if key not in _DEFAULTS:
        _DEFAULTS[key] = json.loads(zenoh.Config().get_json(key))
    return _DEFAULTS[key]


def _read_config_file(path: str) -> bytes:
    """The bytes of the zenoh config file `path`: a regular file of at most
    :data:`MAX_CONFIG_BYTES`, else InvalidNetConfig saying why (a FIFO is opened without
    waiting for a writer, and nothing of a device or a directory is read)."""
    def bad(why):
        return InvalidNetConfig("zenoh_config", f"{why} {str(path)!r}" if why == "no such file"
                                else f"{str(path)!r}: {why}")
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0))
    except FileNotFoundError:
        raise bad("no such file") from None
    except OSError as exc:
        raise bad(f"cannot open: {exc.strerror}") from None
    st = os.fstat(fd)
    if not stat.S_ISREG(st.st_mode):
        os.close(fd)
        kind = ("a directory" if stat.S_ISDIR(st.st_mode) else
                "a FIFO (named pipe)" if stat.S_ISFIFO(st.st_mode) else
                "a character device" if stat.S_ISCHR(st.st_mode) else
                "a block device" if stat.S_ISBLK(st.st_mode) else
                "a socket" if stat.S_ISSOCK(st.st_mode) else "a special file")
        raise bad(f"is {kind}, not a regular file")
    with os.fdopen(fd, "rb") as f:
        data = f.read(MAX_CONFIG_BYTES + 1)
    if max(st.st_size, len(data)) > MAX_CONFIG_BYTES:
        raise bad(f"{max(st.st_size, len(data))} bytes, above the largest zenoh config "
                  f"file read, {MAX_CONFIG_BYTES >> 20} MiB")
    return data


def _load_config_file(path: str) -> zenoh.Config:
    """``zenoh.Config`` of the file `path` once :func:`_read_config_file` has found it a
    regular file of a bounded size (zenoh then reads it by path: ``from_json5`` of the
    same bytes would lose the line of an error, and yaml is read only by path)."""
    _read_config_file(path)
    return zenoh.Config.from_file(path)


def _base_config(zenoh_config: str | None, fragment: dict | None) -> zenoh.Config:
    """The file (or zenoh's defaults) with the secure fragment inserted on top."""
    if zenoh_config is not None:
        try:
            conf = _load_config_file(zenoh_config)
        except zenoh.ZError as exc:
            raise InvalidNetConfig("zenoh_config", f"cannot load {zenoh_config!r}: {zenoh_message(exc)}") from None
    else:
        conf = zenoh.Config()
    for key, value in _flatten(fragment or {}):
        try:
            conf.insert_json5(key, json.dumps(value))
        except zenoh.ZError as exc:
            raise InvalidNetConfig("keys", f"cannot apply {key}: {zenoh_message(exc)}") from None
    return conf


def _file_value(conf: zenoh.Config, key: str):
    """The value of `key` if the file (or fragment) set it, else None.

    A value equal to zenoh's default is not told apart from no value.
    """
    value = json.loads(conf.get_json(key))
    return None if value == _default(key) else value


def _per_mode(value, mode: str):
    # zenoh accepts a list or {router: [...], peer: [...], client: [...]}
    return value.get(mode, []) if isinstance(value, dict) else value


@dataclass(frozen=True)
class NetConfig:
    """Transport settings of one socmon process.

    Fields left at ``None`` are resolved when the NetConfig is made: from the zenoh config
    file (or the secure fragment of `keys`) when it sets the matching key, else socmon's
    default. After construction every field holds the value the session will use.

    Parameters
    ----------
    run : str or None
        Run id; every key of the run lives under ``socmon/<run>/``. Letters, digits,
        ``_``, ``.``, ``-``. Default: the run of `keys`, else ``"default"``.
    listen : sequence of str or None
        zenoh endpoints to listen on, e.g. ``("tcp/127.0.0.1:7447",)``. Default
        :data:`DEFAULT_LISTEN` (:data:`DEFAULT_SECURE_LISTEN` with `keys`); none in
        client mode (a client only connects).
    connect : sequence of str or None
        Endpoints to connect to. One seed peer is enough: the rest of the mesh is found
        by gossip scouting. Default none.
    multicast : bool or None
        Enable UDP multicast scouting (LAN discovery without seeds). Default False.
    lease_ms : int or None
        Link lease in milliseconds: how fast a silent peer is declared dead. Default
        :data:`DEFAULT_LEASE_MS`.
    zenoh_config : str or None
        Optional zenoh json5 config file, applied first.
    keys : str or Path or None
        Key directory made by ``socmon keys init``: the process then talks TLS with
        mutual authentication only, under the run's access control (see
        :mod:`broker_free_net.security`). Requires `identity`.
    identity : str or None
        Process name whose credentials to use: ``"world"``, ``"agent-<i>"``,
        ``"monitor"``, ``"operator"`` or ``"recorder"``.
    mode : str or None
        zenoh mode, ``"peer"`` (default: every process links to every other) or
        ``"client"`` (one link, to the first reachable router of `connect`; see
        :mod:`broker_free_net.router`). Not with `keys`: the access control names the
        process at the other end of each link, which a router would hide.

    Examples
    --------
    >>> NetConfig(run="demo", connect=["tcp/127.0.0.1:7447"]).listen
    ('tcp/127.0.0.1:0',)
    """

    run: str | None = None
    listen: tuple[str, ...] | None = None
    connect: tuple[str, ...] | None = None
    multicast: bool | None = None
    lease_ms: int | None = None
    zenoh_config: str | None = field(default=None)
    keys: str | None = None
    identity: str | None = None
    mode: str | None = None

    def __post_init__(self):
        from .security import InvalidKeys, load_fragment, load_key_set

        put = lambda name, value: object.__setattr__(self, name, value)  # noqa: E731
        if self.zenoh_config is not None:
            if not isinstance(self.zenoh_config, (str, Path)):
                raise InvalidNetConfig("zenoh_config", f"expected a path, got {type(self.zenoh_config).__name__}")
            path = Path(self.zenoh_config)
            _read_config_file(str(path))   # a missing, special or huge file named at once
            put("zenoh_config", str(path))
        fragment = None
        if self.keys is not None:
            if not isinstance(self.keys, (str, Path)):
                raise InvalidNetConfig("keys", f"expected a directory, got {type(self.keys).__name__}")
            if self.identity is None:
                raise InvalidNetConfig("identity", "keys given without the identity whose credentials to use")
            try:
                key_set = load_key_set(self.keys)
                if self.run is None:
                    put("run", key_set.run)
                fragment = load_fragment(self.keys, self.identity, self.run)
            except InvalidKeys as exc:
                raise InvalidNetConfig("keys", str(exc).removeprefix("keys: ")) from None
            put("keys", str(key_set.dir))
        elif self.identity is not None:
            raise InvalidNetConfig("keys", f"identity {self.identity!r} given without keys")
        if self.run is None:
            put("run", "default")
        if not isinstance(self.run, str) or not _RUN_RE.match(self.run):
            raise InvalidNetConfig("run", f"invalid run id {self.run!r} (letters, digits, '_', '.', '-')")

        conf = _base_config(self.zenoh_config, fragment) if (self.zenoh_config or fragment) else None
        src = "zenoh_config"

        def from_file(name, key):
            return None if conf is None else _file_value(conf, key)

        if self.mode is None:
            put("mode", from_file("mode", "mode") or "peer")
            if self.mode not in _MODES:
                raise InvalidNetConfig(src, f"mode {self.mode!r} is not one of {', '.join(_MODES)}")
        elif self.mode not in _MODES:
            raise InvalidNetConfig("mode", f"{self.mode!r} is not one of {', '.join(_MODES)}")
        if self.mode == "client" and fragment is not None:
            raise InvalidNetConfig("mode", "client mode cannot be used with keys: the access "
                                           "control names the process at the other end of a "
                                           "link, and through a router that is the router")
        for name, key in (("listen", "listen/endpoints"), ("connect", "connect/endpoints")):
            value = getattr(self, name)
            if value is None:
                found = from_file(name, key)
                if found is not None:
                    try:
                        put(name, _check_endpoints(name, _per_mode(found, self.mode)))
                    except InvalidNetConfig as exc:
                        raise InvalidNetConfig(src, f"{key}: {exc}") from None
                else:
                    default = (DEFAULT_SECURE_LISTEN if fragment else DEFAULT_LISTEN) \
                        if name == "listen" and self.mode != "client" else ()
                    put(name, default)
            else:
                put(name, _check_endpoints(name, value))
        if self.multicast is None:
            put("multicast", bool(from_file("multicast", "scouting/multicast/enabled") or False))
        if not isinstance(self.multicast, bool):
            raise InvalidNetConfig("multicast", f"expected bool, got {type(self.multicast).__name__}")
        if self.lease_ms is None:
            put("lease_ms", from_file("lease_ms", "transport/link/tx/lease") or DEFAULT_LEASE_MS)
        if isinstance(self.lease_ms, bool) or not isinstance(self.lease_ms, int):
            raise InvalidNetConfig("lease_ms", f"expected int, got {type(self.lease_ms).__name__}")
        if not 100 <= self.lease_ms <= 600_000:
            raise InvalidNetConfig("lease_ms", f"{self.lease_ms} out of range [100, 600000]")
        if fragment is not None:
            for name in ("listen", "connect"):
                plain = [ep for ep in getattr(self, name) if not ep.startswith("tls/")]
                if plain:
                    raise InvalidNetConfig(name, f"{plain[0]!r}: with keys every endpoint is tls/ "
                                                 f"(e.g. tls/127.0.0.1:7447)")
        elif self.zenoh_config is None:
            # nothing gives this session a certificate: a tls link could never be made,
            # and zenoh would keep retrying it in silence
            for name in ("listen", "connect"):
                tls = [ep for ep in getattr(self, name) if ep.startswith("tls/")]
                if tls:
                    raise InvalidNetConfig(name, f"{tls[0]!r}: a tls/ endpoint needs the run's "
                                                 "keys (--keys DIR, or --attach of a --secure "
                                                 "run)")

    def fragment(self) -> dict | None:
        """The secure zenoh config fragment of this process (None without `keys`)."""
        if self.keys is None:
            return None
        from .security import load_fragment

        return load_fragment(self.keys, self.identity, self.run)


def build_zenoh_config(net: NetConfig) -> zenoh.Config:
    """Build the ``zenoh.Config`` of a socmon peer.

    Keys set by socmon (:data:`SOCMON_KEYS`), from the resolved fields of `net`:
    ``mode``; ``listen/endpoints``; ``connect/endpoints``; ``scouting/multicast/enabled``;
    ``transport/link/tx/lease``. Unless the config file sets them:
    ``scouting/gossip/enabled`` = true; ``transport/link/tx/keep_alive`` = 4 (keep-alives
    per lease); ``transport/link/rx/max_message_size`` = :data:`MAX_MESSAGE_BYTES`;
    ``transport/shared_memory/enabled`` = false; ``connect/retry`` = :data:`CONNECT_RETRY`;
    ``timestamping/enabled`` = true (publishers' caches need it); in
    client mode with one connect endpoint ``connect/timeout_ms`` =
    :data:`CLIENT_CONNECT_TIMEOUT_MS`.
    With ``net.keys``, the process's secure fragment (TLS, mTLS, access control, connect
    timeout) is applied over the file. Everything else comes from ``net.zenoh_config`` or
    the zenoh defaults.

    Parameters
    ----------
    net : NetConfig

    Returns
    -------
    zenoh.Config
    """
    if not isinstance(net, NetConfig):
        raise TypeError(f"net: expected NetConfig, got {type(net).__name__}")
    conf = _base_config(net.zenoh_config, net.fragment())
    has_file = net.zenoh_config is not None
    fixed = {
        "scouting/gossip/enabled": True,
        "transport/link/tx/keep_alive": KEEP_ALIVES_PER_LEASE,
        "transport/link/rx/max_message_size": MAX_MESSAGE_BYTES,
        # socmon messages are far below zenoh's 3 kB shared-memory threshold; with shared
        # memory on, any local process sending larger payloads made each receiver map its
        # 16 MB pool (RSS +19 MB in scripts/bench_hostile.py)
        "transport/shared_memory/enabled": False,
        # a link lost to a pause or a partition is tried again every 250-500 ms (zenoh's
        # default backs off to 4 s: an agent cut off by a 3 s pause of the world came back
        # only after the monitor had convicted it)
        "connect/retry": CONNECT_RETRY,
        # a publisher's cache of its last samples (Peer.publisher(cache=...), for
        # receivers that subscribe late) needs the samples timestamped
        "timestamping/enabled": True,
    }
    if net.mode == "client" and len(net.connect) == 1:
        fixed["connect/timeout_ms"] = CLIENT_CONNECT_TIMEOUT_MS
    overrides = {
        "mode": net.mode,
        "listen/endpoints": list(net.listen),
        "connect/endpoints": list(net.connect),
        "scouting/multicast/enabled": net.multicast,
        "transport/link/tx/lease": net.lease_ms,
    }
    for key, value in fixed.items():
        if not (has_file and _file_value(conf, key) is not None):
            overrides[key] = value
    for key, value in overrides.items():
        conf.insert_json5(key, json.dumps(value))
    return conf


_NET_HELP = (
    "socmon sets these zenoh keys: mode (peer), listen/endpoints, connect/endpoints, "
    "scouting/multicast/enabled, transport/link/tx/lease, and, unless the --zenoh-config "
    f"file sets them, scouting/gossip/enabled (true), transport/link/tx/keep_alive "
    f"({KEEP_ALIVES_PER_LEASE}), transport/link/rx/max_message_size ({MAX_MESSAGE_BYTES}) "
    "transport/shared_memory/enabled (false), connect/retry (250 ms, backing off to "
    "500 ms) and timestamping/enabled (true). "
    "A value in the --zenoh-config file is kept unless its flag is given; every other key "
    "of the file passes through. --keys adds TLS with mutual authentication and access "
    "control (see docs/security.md)."
)

_ROUTER_NET_HELP = (_NET_HELP.replace("mode (peer)", "mode (router)")
                    .split(" --keys adds")[0])


def add_net_arguments(parser: argparse.ArgumentParser,
                      router_listen: str | None = None) -> argparse.ArgumentParser:
    """Add the transport flags to an argparse parser.

    Flags: ``--run``, ``--listen`` (repeatable), ``--connect`` (repeatable),
    ``--mode``, ``--multicast``, ``--zenoh-config``, ``--lease-ms``, ``--keys``. Every flag defaults to
    None (not given), so that a value of the ``--zenoh-config`` file is kept.

    With ``router_listen`` (a router's default endpoint) the help is a router's: it does
    not show ``--run`` (a router routes every run), ``--mode`` (it is a router) or
    ``--keys`` (secured runs use the peer mesh), which stay accepted so that the command
    can say why they do not apply.
    """
    router = router_listen is not None
    group = parser.add_argument_group("network", _ROUTER_NET_HELP if router else _NET_HELP)
    hidden = argparse.SUPPRESS
    group.add_argument("--run", default=None,
                       help=hidden if router else "run id (key prefix socmon/<run>/; default: "
                       "the run of --keys, else 'default')")
    group.add_argument("--listen", action="append", metavar="ENDPOINT",
                       help=f"zenoh endpoint to listen on (repeatable; default {router_listen})"
                       if router else
                       f"zenoh endpoint to listen on (repeatable; default {DEFAULT_LISTEN[0]}, "
                       f"{DEFAULT_SECURE_LISTEN[0]} with --keys)")
    group.add_argument("--connect", action="append", metavar="ENDPOINT",
                       help="another router to join (repeatable)" if router else
                       "seed endpoint to connect to (repeatable); in client mode, the "
                       "routers to try in order")
    group.add_argument("--mode", choices=_PROCESS_MODES, default=None,
                       help=hidden if router else "peer (default): link to every other "
                       "process; client: one link, to a router (socmon router) given by "
                       "--connect")
    group.add_argument("--multicast", action="store_true", default=None,
                       help="enable multicast scouting (LAN)")
    group.add_argument("--zenoh-config", metavar="FILE", help="zenoh json5 config file applied first")
    group.add_argument("--lease-ms", type=int, default=None,
                       help=f"link lease in ms (default {DEFAULT_LEASE_MS})")
    group.add_argument("--keys", metavar="DIR",
                       help=hidden if router else "key directory of the run (socmon keys "
                       "init): TLS, mutual authentication and access control")
    return parser


def net_config_from_args(args: argparse.Namespace, identity: str | None = None) -> NetConfig:
    """Build a :class:`NetConfig` from arguments added by :func:`add_net_arguments`.

    Parameters
    ----------
    args : argparse.Namespace
    identity : str or None
        The process name whose credentials ``--keys`` holds (e.g. ``"agent-3"``; socmon's
        names: :func:`agent.protocol.topics.identity_name`); required with ``--keys``.

    Raises
    ------
    InvalidNetConfig
        Naming the field, which is also the flag (``zenoh_config`` -> ``--zenoh-config``).
    """
    keys = getattr(args, "keys", None)
    if keys is not None and identity is None:
        raise InvalidNetConfig("keys", "this command does not say whose credentials to use "
                                       "(net_config_from_args needs identity=)")
    return NetConfig(
        run=args.run,
        listen=tuple(args.listen) if args.listen else None,
        connect=tuple(args.connect) if args.connect else None,
        multicast=args.multicast,
        lease_ms=getattr(args, "lease_ms", None),
        zenoh_config=args.zenoh_config,
        keys=keys,
        identity=identity if keys is not None else None,
        mode=getattr(args, "mode", None),
    )

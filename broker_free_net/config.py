"""Session configuration: plain values -> ``zenoh.Config``.

The order of precedence is: zenoh defaults < optional zenoh config file
(json5) < the values of :class:`NetConfig`. Only the keys listed in
:func:`build_zenoh_config` are overridden; everything else in the file
passes through untouched (TLS, interfaces, queue sizes, ...).
"""

from __future__ import annotations

import argparse
import json
import re
from dataclasses import dataclass, field
from pathlib import Path

import zenoh

__all__ = [
    "DEFAULT_LEASE_MS",
    "DEFAULT_LISTEN",
    "MAX_MESSAGE_BYTES",
    "InvalidNetConfig",
    "NetConfig",
    "add_net_arguments",
    "build_zenoh_config",
    "net_config_from_args",
]

#: Default link lease. A peer that stops answering keep-alives (hung, killed,
#: cable pulled) is declared gone after at most this long, and its liveliness
#: tokens are withdrawn. zenoh's own default is 10 s.
DEFAULT_LEASE_MS = 1000
#: Keep-alive messages sent per lease period (zenoh ``transport/link/tx/keep_alive``).
KEEP_ALIVES_PER_LEASE = 4
#: Default listen endpoint: loopback, port chosen by the OS.
DEFAULT_LISTEN = ("tcp/127.0.0.1:0",)
#: Largest message zenoh will reassemble (``transport/link/rx/max_message_size``).
#: zenoh's default is 1 GiB; socmon messages are a few hundred bytes.
MAX_MESSAGE_BYTES = 1 << 20

_RUN_RE = re.compile(r"^[A-Za-z0-9_.\-]+$")
# <protocol>/<address>[?<metadata>][#<config>]
_ENDPOINT_RE = re.compile(r"^[a-z][a-z0-9+\-]*/\S+$")


class InvalidNetConfig(ValueError):
    """A network configuration value is invalid.

    Attributes
    ----------
    field : str
        Name of the offending field (as in :class:`NetConfig`).
    """

    def __init__(self, field: str, message: str):
        self.field = field
        super().__init__(f"{field}: {message}")


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
    return endpoints


@dataclass(frozen=True)
class NetConfig:
    """Transport settings of one socmon process.

    Parameters
    ----------
    run : str
        Run id; every key of the run lives under ``socmon/<run>/``. Letters,
        digits, ``_``, ``.``, ``-``.
    listen : sequence of str
        zenoh endpoints to listen on, e.g. ``("tcp/127.0.0.1:7447",)``.
    connect : sequence of str
        Endpoints to connect to. One seed peer is enough: the rest of the
        mesh is found by gossip scouting.
    multicast : bool
        Enable UDP multicast scouting (LAN discovery without seeds).
    lease_ms : int
        Link lease in milliseconds: how fast a silent peer is declared dead.
    config_file : str or None
        Optional zenoh json5 config file, applied before the values above.
    """

    run: str = "default"
    listen: tuple[str, ...] = DEFAULT_LISTEN
    connect: tuple[str, ...] = ()
    multicast: bool = False
    lease_ms: int = DEFAULT_LEASE_MS
    config_file: str | None = field(default=None)

    def __post_init__(self):
        if not isinstance(self.run, str) or not _RUN_RE.match(self.run):
            raise InvalidNetConfig("run", f"invalid run id {self.run!r} (letters, digits, '_', '.', '-')")
        object.__setattr__(self, "listen", _check_endpoints("listen", self.listen))
        object.__setattr__(self, "connect", _check_endpoints("connect", self.connect))
        if not isinstance(self.multicast, bool):
            raise InvalidNetConfig("multicast", f"expected bool, got {type(self.multicast).__name__}")
        if isinstance(self.lease_ms, bool) or not isinstance(self.lease_ms, int):
            raise InvalidNetConfig("lease_ms", f"expected int, got {type(self.lease_ms).__name__}")
        if not 100 <= self.lease_ms <= 600_000:
            raise InvalidNetConfig("lease_ms", f"{self.lease_ms} out of range [100, 600000]")
        if self.config_file is not None:
            path = Path(self.config_file)
            if not path.is_file():
                raise InvalidNetConfig("config_file", f"no such file {self.config_file!r}")
            object.__setattr__(self, "config_file", str(path))


def build_zenoh_config(net: NetConfig) -> zenoh.Config:
    """Build the ``zenoh.Config`` of a socmon peer.

    Overridden keys (everything else comes from ``net.config_file`` or the
    zenoh defaults):

    ``mode`` = ``"peer"``; ``listen/endpoints``; ``connect/endpoints``;
    ``scouting/multicast/enabled``; ``scouting/gossip/enabled`` = true;
    ``transport/link/tx/lease`` = ``net.lease_ms``;
    ``transport/link/tx/keep_alive`` = 4 (keep-alives per lease);
    ``transport/link/rx/max_message_size`` = :data:`MAX_MESSAGE_BYTES`.

    Parameters
    ----------
    net : NetConfig

    Returns
    -------
    zenoh.Config
    """
    if not isinstance(net, NetConfig):
        raise TypeError(f"net: expected NetConfig, got {type(net).__name__}")
    if net.config_file is not None:
        try:
            conf = zenoh.Config.from_file(net.config_file)
        except zenoh.ZError as exc:
            raise InvalidNetConfig("config_file", f"cannot load {net.config_file!r}: {exc}") from exc
    else:
        conf = zenoh.Config()
    overrides = {
        "mode": "peer",
        "listen/endpoints": list(net.listen),
        "connect/endpoints": list(net.connect),
        "scouting/multicast/enabled": net.multicast,
        "scouting/gossip/enabled": True,
        "transport/link/tx/lease": net.lease_ms,
        "transport/link/tx/keep_alive": KEEP_ALIVES_PER_LEASE,
        "transport/link/rx/max_message_size": MAX_MESSAGE_BYTES,
    }
    for key, value in overrides.items():
        conf.insert_json5(key, json.dumps(value))
    return conf


def add_net_arguments(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """Add the transport flags to an argparse parser.

    Flags: ``--run``, ``--listen`` (repeatable), ``--connect`` (repeatable),
    ``--multicast``, ``--zenoh-config``, ``--lease-ms``.
    """
    group = parser.add_argument_group("network")
    group.add_argument("--run", default="default", help="run id (key prefix socmon/<run>/)")
    group.add_argument("--listen", action="append", metavar="ENDPOINT",
                       help=f"zenoh endpoint to listen on (repeatable; default {DEFAULT_LISTEN[0]})")
    group.add_argument("--connect", action="append", metavar="ENDPOINT",
                       help="seed endpoint to connect to (repeatable)")
    group.add_argument("--multicast", action="store_true", help="enable multicast scouting (LAN)")
    group.add_argument("--zenoh-config", metavar="FILE", help="zenoh json5 config file applied first")
    group.add_argument("--lease-ms", type=int, default=DEFAULT_LEASE_MS,
                       help=f"link lease in ms (default {DEFAULT_LEASE_MS})")
    return parser


def net_config_from_args(args: argparse.Namespace) -> NetConfig:
    """Build a :class:`NetConfig` from arguments added by :func:`add_net_arguments`."""
    return NetConfig(
        run=args.run,
        listen=tuple(args.listen) if args.listen else DEFAULT_LISTEN,
        connect=tuple(args.connect or ()),
        multicast=bool(args.multicast),
        lease_ms=getattr(args, "lease_ms", DEFAULT_LEASE_MS),
        config_file=args.zenoh_config,
    )

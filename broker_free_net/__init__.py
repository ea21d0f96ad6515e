"""Broker-free transport of socmon: zenoh peer sessions, keys, codec, impairments.

Knows nothing of estimation: never imports :mod:`design` nor :mod:`agent`
(``tests/test_layers.py`` checks it). Submodules:

- :mod:`broker_free_net.config` -- NetConfig and the zenoh.Config builder
- :mod:`broker_free_net.keys` -- key expressions of a run
- :mod:`broker_free_net.codec` -- msgpack wire format and validation
- :mod:`broker_free_net.impair` -- receiver-side link impairments
- :mod:`broker_free_net.peer` -- Peer: session, liveliness token, inboxes
- :mod:`broker_free_net.linger` -- LingerGuard: zenoh links that do not linger on close
- :mod:`broker_free_net.ports` -- listen ports below the ephemeral range
- :mod:`broker_free_net.router` -- socmon router (zenoh router mode)
- :mod:`broker_free_net.security` -- TLS, mutual TLS and access control configs
"""

from .codec import MalformedMessage, MessageStats, Schema, decode, encode, try_decode
from .config import InvalidNetConfig, NetConfig, add_net_arguments, build_zenoh_config, net_config_from_args
from .impair import LinkImpairments, apply_impairment_message, decode_impairment, encode_impairment
from .keys import InvalidKey
from .peer import Inbox, LivelinessEvent, LivelinessWatch, Peer, Received

__all__ = [
    "Inbox",
    "InvalidKey",
    "InvalidNetConfig",
    "LinkImpairments",
    "LivelinessEvent",
    "LivelinessWatch",
    "MalformedMessage",
    "MessageStats",
    "NetConfig",
    "Peer",
    "Received",
    "Schema",
    "add_net_arguments",
    "apply_impairment_message",
    "build_zenoh_config",
    "decode",
    "decode_impairment",
    "encode",
    "encode_impairment",
    "net_config_from_args",
    "try_decode",
]

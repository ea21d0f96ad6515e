"""Broker-free transport of socmon: zenoh peer sessions, keys, codec, impairments.

Knows nothing of estimation: never imports :mod:`design` nor :mod:`agent`
(``tests/test_layers.py`` checks it). Submodules:

- :mod:`broker_free_net.config` -- NetConfig and the zenoh.Config builder
- :mod:`broker_free_net.keys` -- key chunks, liveliness-token keys (the topics: :mod:`agent.protocol.topics`)
- :mod:`broker_free_net.codec` -- msgpack wire format and validation
- :mod:`broker_free_net.impair` -- receiver-side link impairments
- :mod:`broker_free_net.peer` -- Peer: session, liveliness token, inboxes
- :mod:`broker_free_net.linger` -- LingerGuard: zenoh links that do not linger on close
- :mod:`broker_free_net.ports` -- listen ports below the ephemeral range
- :mod:`broker_free_net.router` -- socmon router (zenoh router mode)
- :mod:`broker_free_net.security` -- TLS, mutual TLS and access control configs from a caller's rights table
"""

import importlib

#: Where each name of the package lives; imported on first use (PEP 562), so that the pure
#: parts (codec, impair, keys) do not load zenoh's native library: only a session does.
_WHERE = {
    "MalformedMessage": "codec", "MessageStats": "codec", "Schema": "codec",
    "decode": "codec", "encode": "codec", "try_decode": "codec",
    "InvalidNetConfig": "config", "NetConfig": "config", "add_net_arguments": "config",
    "build_zenoh_config": "config", "net_config_from_args": "config",
    "LinkImpairments": "impair", "apply_impairment_message": "impair",
    "decode_impairment": "impair", "encode_impairment": "impair",
    "InvalidKey": "keys",
    "Inbox": "peer", "LivelinessEvent": "peer", "LivelinessWatch": "peer", "Peer": "peer",
    "Received": "peer", "SessionError": "peer",
}


def __getattr__(name):
    module = _WHERE.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(f".{module}", __name__), name)
    globals()[name] = value
    return value


def __dir__():
    return sorted(set(globals()) | set(_WHERE))


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
    "SessionError",
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

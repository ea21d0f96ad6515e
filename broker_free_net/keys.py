"""Generic key-expression pieces: chunk validation and liveliness-token keys.

The transport knows no topic layout of its own: the application names its keys (socmon's
are in :mod:`agent.protocol.topics`). What lives here is what any layout needs:

- :func:`validate_chunk` -- a single key chunk: non-empty, without ``* $ / # ?``,
  whitespace or a leading ``@``;
- :func:`validate_id` -- an id chunk: a non-negative int (written in decimal) or a key chunk;
- the liveliness-token layout of a :class:`~broker_free_net.peer.Peer`:
  ``<prefix>/<role>/<id>/<session>`` under a prefix the caller gives
  (:func:`token_key`, :func:`token_pattern`, :func:`parse_token_key`).
"""

from __future__ import annotations

__all__ = [
    "InvalidKey",
    "parse_token_key",
    "token_key",
    "token_pattern",
    "validate_chunk",
    "validate_id",
    "validate_int_chunk",
]

_FORBIDDEN = set("*$/#?")


class InvalidKey(ValueError):
    """A key, or a part of a key, is malformed.

    Attributes
    ----------
    field : str
        What was being validated (``"run"``, ``"label"``, ``"key"``, ...).
    """

    def __init__(self, field: str, message: str):
        self.field = field
        super().__init__(f"{field}: {message}")


def validate_chunk(value, field: str = "chunk") -> str:
    """Check that `value` is a valid single key chunk and return it.

    Raises
    ------
    InvalidKey
        If `value` is not a str, is empty, contains ``* $ / # ?`` or
        whitespace/control characters, or starts with ``@``.
    """
    if not isinstance(value, str):
        raise InvalidKey(field, f"expected str, got {type(value).__name__}")
    if not value:
        raise InvalidKey(field, "empty")
    bad = _FORBIDDEN.intersection(value)
    if bad:
        raise InvalidKey(field, f"{value!r} contains forbidden character(s) {''.join(sorted(bad))!r}")
    if value.startswith("@"):
        raise InvalidKey(field, f"{value!r} starts with '@' (reserved by zenoh)")
    if any(c.isspace() or not c.isprintable() for c in value):
        raise InvalidKey(field, f"{value!r} contains whitespace or control characters")
    return value


def validate_int_chunk(value, field: str) -> str:
    """A non-negative int (not a bool) as its decimal key chunk.

    >>> validate_int_chunk(12, "agent")
    '12'
    """
    if isinstance(value, bool) or not isinstance(value, int):
        raise InvalidKey(field, f"expected int, got {type(value).__name__}")
    if value < 0:
        raise InvalidKey(field, f"negative {field} id {value}")
    return str(value)


def validate_id(value, field: str = "id") -> str:
    """An id chunk: a non-negative int written in decimal, or a key chunk.

    >>> validate_id(4), validate_id("p12")
    ('4', 'p12')
    """
    if isinstance(value, int) and not isinstance(value, bool):
        return validate_int_chunk(value, "agent")
    return validate_chunk(value, field)


def token_key(prefix: str, role: str, id, session: str) -> str:
    """The liveliness key ``<prefix>/<role>/<id>/<session>``.

    `prefix` is the caller's (checked by zenoh when declared); `id` may be a non-negative
    int or a key chunk; `session` names the zenoh session that declares the token (its
    zid). zenoh aggregates the tokens of one key: a second process declaring the same key
    would be invisible, and the first one's end with it. With the session in the key, two
    processes claiming one id are two tokens, seen.

    >>> token_key("app/r/alive", "agent", 4, "a1b2")
    'app/r/alive/agent/4/a1b2'
    """
    id_chunk = validate_id(id)
    return f"{prefix}/{validate_chunk(role, 'role')}/{id_chunk}/{validate_chunk(session, 'session')}"


def token_pattern(prefix: str) -> str:
    """The liveliness subscription pattern ``<prefix>/**``."""
    return f"{prefix}/**"


def parse_token_key(prefix: str, key) -> tuple[str, str, str]:
    """Extract ``(role, id, session)`` from ``<prefix>/<role>/<id>/<session>``.

    The id is returned as the str chunk.

    >>> parse_token_key("app/r/alive", "app/r/alive/agent/7/ab")
    ('agent', '7', 'ab')
    """
    if not isinstance(key, str):
        key = str(key)  # zenoh.KeyExpr
    head = prefix.split("/")
    parts = key.split("/")
    if len(parts) != len(head) + 3 or parts[:len(head)] != head:
        raise InvalidKey("key", f"{key!r} is not a {prefix}/... key with 3 trailing chunk(s)")
    role, id_chunk, session = parts[len(head):]
    return (validate_chunk(role, "role"), validate_chunk(id_chunk, "id"),
            validate_chunk(session, "session"))

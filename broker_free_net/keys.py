"""Key expressions of a socmon run.

Every key lives under ``socmon/<run>/``::

    socmon/<run>/est/<agent>          estimate published by an agent
    socmon/<run>/sensors              sensor readings of one step, every node (world -> agents)
    socmon/<run>/ctl/<agent>          control message to an agent
    socmon/<run>/status/<agent>       status of an agent
    socmon/<run>/truth                ground truth (world -> recorder; the monitor never reads it)
    socmon/<run>/end                  the world's last step, once it ends (world -> everyone)
    socmon/<run>/impair               impairment changes (socmon inject)
    socmon/<run>/alive/<role>/<id>/<session>  liveliness token of a process (its zid)

Agent ids are non-negative ints written in decimal without leading zeros.
Run ids, labels, roles and liveliness ids are single key chunks: non-empty,
without ``* $ / # ?``, whitespace or a leading ``@``.
"""

from __future__ import annotations

__all__ = [
    "PREFIX",
    "InvalidKey",
    "agent_key",
    "alive_key",
    "alive_pattern",
    "any_agent_pattern",
    "ctl_key",
    "end_key",
    "est_key",
    "impair_key",
    "monitor_events_key",
    "parse_agent_key",
    "parse_alive_key",
    "AgentKeyCache",
    "run_prefix",
    "sensors_key",
    "status_key",
    "truth_key",
    "validate_chunk",
]

PREFIX = "socmon"
AGENT_KINDS = ("est", "ctl", "status")
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


def _agent_chunk(agent) -> str:
    if isinstance(agent, bool) or not isinstance(agent, int):
        raise InvalidKey("agent", f"expected int, got {type(agent).__name__}")
    if agent < 0:
        raise InvalidKey("agent", f"negative agent id {agent}")
    return str(agent)


def run_prefix(run: str) -> str:
    """Return ``socmon/<run>``."""
    return f"{PREFIX}/{validate_chunk(run, 'run')}"


def agent_key(run: str, kind: str, agent: int) -> str:
    """Return ``socmon/<run>/<kind>/<agent>`` for kind in ``est``, ``ctl``, ``status``."""
    if kind not in AGENT_KINDS:
        raise InvalidKey("kind", f"{kind!r} not in {AGENT_KINDS}")
    return f"{run_prefix(run)}/{kind}/{_agent_chunk(agent)}"


def est_key(run: str, agent: int) -> str:
    """Return ``socmon/<run>/est/<agent>``."""
    return agent_key(run, "est", agent)


def ctl_key(run: str, agent: int) -> str:
    """Return ``socmon/<run>/ctl/<agent>``."""
    return agent_key(run, "ctl", agent)


def status_key(run: str, agent: int) -> str:
    """Return ``socmon/<run>/status/<agent>``."""
    return agent_key(run, "status", agent)


def any_agent_pattern(run: str, kind: str) -> str:
    """Return the subscription pattern ``socmon/<run>/<kind>/*``."""
    if kind not in AGENT_KINDS:
        raise InvalidKey("kind", f"{kind!r} not in {AGENT_KINDS}")
    return f"{run_prefix(run)}/{kind}/*"


def sensors_key(run: str) -> str:
    """Return ``socmon/<run>/sensors``: the world's readings of every node, one message a
    step (one message instead of one per node: the cost of a step is mostly per message)."""
    return f"{run_prefix(run)}/sensors"


def truth_key(run: str) -> str:
    """Return ``socmon/<run>/truth``."""
    return f"{run_prefix(run)}/truth"


def impair_key(run: str) -> str:
    """Return ``socmon/<run>/impair``."""
    return f"{run_prefix(run)}/impair"


def end_key(run: str) -> str:
    """``socmon/<run>/end``: the world's word that the run is over (its token alone may go
    because it was paused or cut off)."""
    return f"{run_prefix(run)}/end"


def monitor_events_key(run: str) -> str:
    """Return ``socmon/<run>/monitor/events`` (the monitor's verdicts, for watchers)."""
    return f"{run_prefix(run)}/monitor/events"


def alive_key(run: str, role: str, id, session: str) -> str:
    """Return the liveliness key ``socmon/<run>/alive/<role>/<id>/<session>``.

    `id` may be a non-negative int or a key chunk; `session` names the zenoh session that
    declares the token (its zid). zenoh aggregates the tokens of one key: a second
    process declaring the same key would be invisible, and the first one's end with it.
    With the session in the key, two processes claiming one id are two tokens, seen.

    >>> alive_key("r", "agent", 4, "a1b2")
    'socmon/r/alive/agent/4/a1b2'
    """
    id_chunk = _agent_chunk(id) if isinstance(id, int) and not isinstance(id, bool) else validate_chunk(id, "id")
    return (f"{run_prefix(run)}/alive/{validate_chunk(role, 'role')}/{id_chunk}/"
            f"{validate_chunk(session, 'session')}")


def alive_pattern(run: str) -> str:
    """Return the liveliness subscription pattern ``socmon/<run>/alive/**``."""
    return f"{run_prefix(run)}/alive/**"


def _split(run: str, key, n_after: int, kind: str) -> list[str]:
    if not isinstance(key, str):
        key = str(key)  # zenoh.KeyExpr
    parts = key.split("/")
    if len(parts) != 3 + n_after or parts[0] != PREFIX or parts[1] != run or parts[2] != kind:
        raise InvalidKey("key", f"{key!r} is not a socmon/{run}/{kind}/... key with {n_after} trailing chunk(s)")
    return parts[3:]


def parse_agent_key(run: str, kind: str, key) -> int:
    """Extract the agent id from ``socmon/<run>/<kind>/<agent>``.

    Raises
    ------
    InvalidKey
        If the key has another run, kind or shape, or the agent chunk is not
        a canonical non-negative decimal int.
    """
    (chunk,) = _split(run, key, 1, kind)
    if not (chunk.isascii() and chunk.isdigit()) or (len(chunk) > 1 and chunk[0] == "0") or len(chunk) > 9:
        raise InvalidKey("agent", f"{chunk!r} in {key!s} is not a canonical agent id")
    return int(chunk)


def parse_alive_key(run: str, key) -> tuple[str, str, str]:
    """Extract ``(role, id, session)`` from ``socmon/<run>/alive/<role>/<id>/<session>``.

    The id is returned as the str chunk; agents use ``int(id)``.
    """
    role, id_chunk, session = _split(run, key, 3, "alive")
    return (validate_chunk(role, "role"), validate_chunk(id_chunk, "id"),
            validate_chunk(session, "session"))


class AgentKeyCache:
    """``socmon/<run>/<kind>/<agent>`` -> agent id, parsed once per key and kept only for
    the ``known`` ids (a stream of made-up keys cannot grow it).

    >>> c = AgentKeyCache("r", "est", known={1, 2})
    >>> c.agent_of("socmon/r/est/2"), c.agent_of("socmon/r/est/9"), c.agent_of("socmon/r/x/1")
    (2, 9, None)
    >>> len(c)
    1
    """

    def __init__(self, run: str, kind: str, known):
        self.run, self.kind, self.known = run, kind, known
        self._ids: dict = {}

    def agent_of(self, key) -> int | None:
        """The agent id of ``key``, or None when it is not such a key."""
        agent = self._ids.get(key)
        if agent is None:
            try:
                agent = parse_agent_key(self.run, self.kind, key)
            except InvalidKey:
                return None
            if agent in self.known:
                self._ids[key] = agent
        return agent

    def __len__(self) -> int:
        return len(self._ids)

"""socmon's topics and process roles: the key expressions of a run and who may use which.

Every key lives under ``socmon/<run>/``::

    socmon/<run>/est/<agent>          estimate published by an agent
    socmon/<run>/sensors              sensor readings of one step, every node (world -> agents)
    socmon/<run>/ctl/<agent>          control message to an agent
    socmon/<run>/status/<agent>       status of an agent
    socmon/<run>/truth                ground truth (world -> recorder; the monitor never reads it)
    socmon/<run>/end                  the world's last step, once it ends (world -> everyone)
    socmon/<run>/impair               impairment changes (socmon inject)
    socmon/<run>/monitor/events       the monitor's verdicts, for watchers
    socmon/<run>/alive/<role>/<id>/<session>  liveliness token of a process (its zid)

Agent ids are non-negative ints written in decimal without leading zeros.
Run ids, labels, roles and liveliness ids are single key chunks: non-empty,
without ``* $ / # ?``, whitespace or a leading ``@``
(:func:`broker_free_net.keys.validate_chunk`).

Processes of a secured run and their names (the CN of their certificate)::

    world        puts socmon/<run>/sensors, socmon/<run>/truth, socmon/<run>/end
    agent-<i>    puts socmon/<run>/est/<i>, socmon/<run>/status/<i>
    monitor      puts socmon/<run>/ctl/*, socmon/<run>/monitor/**
    operator     puts socmon/<run>/impair          (socmon inject)
    recorder     puts nothing                       (socmon up's recorder, socmon watch)

Everyone may subscribe to any key of the run and watch liveliness; a process may declare
only its own liveliness token (``socmon/<run>/alive/<role>/<id>/<zid>`` of its role; the
last chunk is the declaring session's zid, any value the identity chooses). The transport
turns this table into zenoh's ``access_control`` (:func:`access_control`,
:func:`broker_free_net.security.build_access_control`).

Pure: this module does not load zenoh (:func:`open_peer` imports it when called).
"""

from __future__ import annotations

import re

from broker_free_net import security
from broker_free_net.keys import (
    InvalidKey,
    parse_token_key,
    token_key,
    token_pattern,
    validate_chunk,
    validate_int_chunk,
)
from broker_free_net.security import InvalidKeys, Permissions

__all__ = [
    "AGENT_KINDS",
    "PREFIX",
    "ROLES",
    "AgentKeyCache",
    "access_control",
    "agent_key",
    "alive_key",
    "alive_pattern",
    "alive_prefix",
    "any_agent_pattern",
    "ctl_key",
    "end_key",
    "est_key",
    "estimate_subscriptions",
    "identity_name",
    "impair_key",
    "key_set_about",
    "key_set_lines",
    "key_set_mismatch",
    "make_run_keys",
    "monitor_events_key",
    "open_peer",
    "parse_agent_key",
    "parse_alive_key",
    "parse_identity",
    "permissions",
    "put_keys",
    "run_identities",
    "run_pattern",
    "run_prefix",
    "sensors_key",
    "serve_keys",
    "status_key",
    "token_keys",
    "truth_key",
]

PREFIX = "socmon"
AGENT_KINDS = ("est", "ctl", "status")

# --------------------------------------------------------------------------- key expressions


def run_prefix(run: str) -> str:
    """Return ``socmon/<run>``."""
    return f"{PREFIX}/{validate_chunk(run, 'run')}"


def run_pattern(run: str) -> str:
    """Return ``socmon/<run>/**``: every key of the run."""
    return f"{run_prefix(run)}/**"


def agent_key(run: str, kind: str, agent: int) -> str:
    """Return ``socmon/<run>/<kind>/<agent>`` for kind in ``est``, ``ctl``, ``status``."""
    if kind not in AGENT_KINDS:
        raise InvalidKey("kind", f"{kind!r} not in {AGENT_KINDS}")
    return f"{run_prefix(run)}/{kind}/{validate_int_chunk(agent, 'agent')}"


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


def estimate_subscriptions(run: str, sources, history: int) -> dict:
    """``{key expression: history}`` of an agent's estimate subscriptions
    (:meth:`broker_free_net.peer.Peer.subscribe_keys`): ``est/<j>`` for each agent j of
    ``sources`` with the last ``history`` estimates of its publisher's cache, or the
    pattern ``est/*`` (no history) when ``sources`` is None (every agent: a standby).

    >>> estimate_subscriptions("demo", {3, 1}, 64)
    {'socmon/demo/est/1': 64, 'socmon/demo/est/3': 64}
    >>> estimate_subscriptions("demo", None, 64)
    {'socmon/demo/est/*': 0}
    """
    if sources is None:
        return {any_agent_pattern(run, "est"): 0}
    return {est_key(run, j): int(history) for j in sorted(sources)}


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


def alive_prefix(run: str) -> str:
    """Return ``socmon/<run>/alive``: the prefix of the run's liveliness tokens, as
    :class:`broker_free_net.peer.Peer` takes it."""
    return f"{run_prefix(run)}/alive"


def alive_key(run: str, role: str, id, session: str) -> str:
    """Return the liveliness key ``socmon/<run>/alive/<role>/<id>/<session>``.

    `id` may be a non-negative int or a key chunk; `session` names the zenoh session that
    declares the token (its zid); see :func:`broker_free_net.keys.token_key`.

    >>> alive_key("r", "agent", 4, "a1b2")
    'socmon/r/alive/agent/4/a1b2'
    """
    return token_key(alive_prefix(run), role, id, session)


def alive_pattern(run: str) -> str:
    """Return the liveliness subscription pattern ``socmon/<run>/alive/**``."""
    return token_pattern(alive_prefix(run))


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

    >>> parse_alive_key("r", "socmon/r/alive/agent/7/ab")
    ('agent', '7', 'ab')
    """
    return parse_token_key(f"{PREFIX}/{run}/alive", key)


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


def open_peer(net, role: str, id):
    """A :class:`broker_free_net.peer.Peer` for process ``(role, id)`` of run ``net.run``,
    its liveliness token under :func:`alive_prefix`.

    >>> with open_peer(NetConfig(run="demo"), "agent", 3) as peer:     # doctest: +SKIP
    ...     inbox = peer.subscribe(any_agent_pattern("demo", "est"))
    """
    from broker_free_net.config import NetConfig
    from broker_free_net.peer import Peer

    if not isinstance(net, NetConfig):
        raise TypeError(f"net: expected NetConfig, got {type(net).__name__}")
    return Peer(net, role, id, alive_prefix=alive_prefix(net.run))


# --------------------------------------------------------------------------- roles and rights

#: The process roles of a run (the CN of a certificate is the role, or ``agent-<i>``).
ROLES = ("world", "agent", "monitor", "operator", "recorder")
_AGENT_RE = re.compile(r"^agent-([1-9][0-9]{0,8})$")
#: Liveliness roles (``open_peer(net, role, id)``) each identity may declare a token for.
_TOKEN_ROLES = {"world": ("world",), "monitor": ("monitor",), "operator": ("inject", "operator"),
                "recorder": ("recorder", "watch")}


def identity_name(role: str, id=None) -> str:
    """The certificate name of a process: ``"agent-3"`` for an agent, else the role.

    >>> identity_name("agent", 3), identity_name("world"), identity_name("operator")
    ('agent-3', 'world', 'operator')
    """
    if role not in ROLES:
        raise InvalidKeys("role", f"{role!r} is not one of {', '.join(ROLES)}")
    if role == "agent":
        if isinstance(id, bool) or not isinstance(id, int) or id < 1:
            raise InvalidKeys("id", f"an agent needs a positive int id, got {id!r}")
        return f"agent-{id}"
    return role


def parse_identity(name: str) -> tuple[str, int | None]:
    """``"agent-3"`` -> ``("agent", 3)``; ``"world"`` -> ``("world", None)``.

    >>> parse_identity("agent-12"), parse_identity("monitor")
    (('agent', 12), ('monitor', None))
    """
    if not isinstance(name, str):
        raise InvalidKeys("name", f"expected str, got {type(name).__name__}")
    m = _AGENT_RE.match(name)
    if m:
        return "agent", int(m.group(1))
    if name in ROLES and name != "agent":
        return name, None
    raise InvalidKeys("name", f"{name!r} is not a process name (world, agent-<i>, monitor, operator, recorder)")


def run_identities(n_agents: int) -> tuple[str, ...]:
    """Every process name of a run with agents 1..`n_agents` (active and standby).

    >>> run_identities(2)
    ('world', 'agent-1', 'agent-2', 'monitor', 'operator', 'recorder')
    """
    if isinstance(n_agents, bool) or not isinstance(n_agents, int) or n_agents < 1:
        raise InvalidKeys("agents", f"expected a positive int, got {n_agents!r}")
    return ("world", *(f"agent-{i}" for i in range(1, n_agents + 1)), "monitor", "operator", "recorder")


def put_keys(run: str, name: str) -> list[str]:
    """Key expressions process `name` may put (publish) in run `run`.

    >>> put_keys("r", "agent-2")
    ['socmon/r/est/2', 'socmon/r/status/2']
    >>> put_keys("r", "recorder")
    []
    """
    security.check_run(run)
    role, i = parse_identity(name)
    p = f"{PREFIX}/{run}"
    return {
        "world": [f"{p}/sensors", f"{p}/truth", f"{p}/end"],
        "agent": [f"{p}/est/{i}", f"{p}/status/{i}"],
        "monitor": [f"{p}/ctl/*", f"{p}/monitor/**"],
        "operator": [f"{p}/impair"],
        "recorder": [],
    }[role]


def serve_keys(run: str, name: str) -> list[str]:
    """Key expressions process `name` may answer queries on: an agent's estimate
    publisher's cache of its last estimates (zenoh's advanced publisher, under
    ``<key>/@adv/**``: ``@`` chunks are matched only verbatim), for a receiver that starts
    listening to it late (:func:`estimate_subscriptions`).

    >>> serve_keys("r", "agent-2"), serve_keys("r", "world")
    (['socmon/r/est/2', 'socmon/r/est/2/@adv/**'], [])
    """
    security.check_run(run)
    role, i = parse_identity(name)
    # the cache's queryable is declared under @adv; its replies carry the samples' key
    return [f"{PREFIX}/{run}/est/{i}", f"{PREFIX}/{run}/est/{i}/@adv/**"] \
        if role == "agent" else []


def token_keys(run: str, name: str) -> list[str]:
    """Liveliness tokens process `name` may declare.

    >>> token_keys("r", "agent-2"), token_keys("r", "operator")
    (['socmon/r/alive/agent/2/*'], ['socmon/r/alive/inject/*/*', 'socmon/r/alive/operator/*/*'])
    """
    security.check_run(run)
    role, i = parse_identity(name)
    if role == "agent":
        return [f"{PREFIX}/{run}/alive/agent/{i}/*"]
    return [f"{PREFIX}/{run}/alive/{r}/*/*" for r in _TOKEN_ROLES[role]]


def permissions(run: str, names) -> dict[str, Permissions]:
    """The rights table of a run: process name -> what it may put and declare, in order.

    >>> permissions("r", ["world", "agent-1"])["agent-1"].put
    ('socmon/r/est/1', 'socmon/r/status/1')
    """
    security.check_run(run)
    names = list(names)
    if not names:
        raise InvalidKeys("names", "no process names")
    for n in names:
        parse_identity(n)
    if len(set(names)) != len(names):
        raise InvalidKeys("names", "a name is listed twice")
    return {n: Permissions(put=tuple(put_keys(run, n)), tokens=tuple(token_keys(run, n)),
                           serve=tuple(serve_keys(run, n))) for n in names}


def access_control(run: str, names) -> dict:
    """The zenoh ``access_control`` block of every process of a run: the :func:`permissions`
    of `names`, every one of them subscribing within ``socmon/<run>/**``
    (:func:`broker_free_net.security.build_access_control`)."""
    return security.build_access_control(run_pattern(run), permissions(run, names))


def key_set_lines(ks, endpoints: dict) -> list:
    """What ``socmon keys`` prints of key set ``ks`` (a
    :class:`broker_free_net.security.KeySet`) whose manifest lists ``endpoints``."""
    agents = [n for n in ks.names if n.startswith("agent-")]
    lines = [f"key set of run {ks.run} in {ks.dir}",
             f"  CA sha256 {ks.ca_fingerprint}, certificates valid until {ks.not_after}",
             f"  processes: world, {agents[0]}..{agents[-1]}, monitor, operator, recorder"
             if agents else f"  processes: {', '.join(ks.names)}"]
    if "scenario_digest" in ks.about:
        a = ks.about
        lines.append(f"  made for scenario {a.get('scenario')} (digest {a.get('scenario_digest')}, "
                     f"{a.get('agents')} agents, {a.get('standby')} standby)")
    else:
        lines.append("  made for no recorded scenario (a key set made before key sets "
                     "recorded theirs)")
    lines += [f"  {name:>10} listens on {ep}" for name, ep in endpoints.items()]
    lines.append(f"  start each process with --keys {ks.dir} (its own credentials are chosen "
                 "by role)")
    return lines


def make_run_keys(dir, run: str, names, scenario=None, **kwargs):
    """:func:`broker_free_net.security.make_run_keys` with the run's rights table: a CA, a
    certificate and a zenoh config (TLS, mTLS, :func:`access_control`) per process of `names`
    (e.g. :func:`run_identities` ``(M)``), recording `scenario` when given
    (:func:`key_set_about`); keyword arguments are passed on."""
    if scenario is not None:
        kwargs["about"] = key_set_about(scenario)
    return security.make_run_keys(dir, run, permissions(run, names), scope=run_pattern(run), **kwargs)


def key_set_about(scenario) -> dict:
    """What a key set records of the scenario it is made for: its name, its digest (what
    determines the estimator) and its agents, active and standby (whose certificates it
    holds).

    >>> from design.scenario import load_scenario
    >>> about = key_set_about(load_scenario("paper-14"))
    >>> about["scenario"], about["agents"], about["standby"]
    ('paper-14', 3, 1)
    """
    return {"scenario": scenario.name, "scenario_digest": scenario.digest(),
            "agents": int(scenario.N), "standby": int(scenario.standby)}


def key_set_mismatch(ks, scenario) -> str | None:
    """Why key set ``ks`` (a :class:`broker_free_net.security.KeySet`) was not made for
    ``scenario``, or None when it was; ``""`` when the key set does not say (made before
    key sets recorded their scenario).

    >>> import tempfile, pathlib
    >>> from design.scenario import load_scenario
    >>> d = pathlib.Path(tempfile.mkdtemp()) / "k"
    >>> ks = make_run_keys(d, "demo", run_identities(4), load_scenario("paper-14"))
    >>> key_set_mismatch(ks, load_scenario("paper-14")) is None
    True
    >>> print(key_set_mismatch(ks, load_scenario("paper-14-live")))  # doctest: +ELLIPSIS
    made for scenario paper-14 (digest ..., 3 agents, 1 standby), not for scenario paper-14-live (digest ..., 3 agents, 1 standby)
    """
    a = ks.about
    if "scenario_digest" not in a:
        return ""
    mine = key_set_about(scenario)
    if all(a.get(k) == mine[k] for k in ("scenario_digest", "agents", "standby")):
        return None
    return (f"made for scenario {a.get('scenario')} (digest {a.get('scenario_digest')}, "
            f"{a.get('agents')} agents, {a.get('standby')} standby), not for scenario "
            f"{mine['scenario']} (digest {mine['scenario_digest']}, {mine['agents']} agents, "
            f"{mine['standby']} standby)")

"""Scenarios: one deployment of the social system, its sensors and the agent network.

A scenario is a frozen :class:`Scenario`; it is read from a TOML file (or a built-in name)
by :func:`load_scenario`, which reports every violated invariant at once, naming the
field. Agents are numbered 1..N wherever a person sees them; inside :class:`Scenario`
they are rows 0..N-1 of ``W``. Nodes are named by label.

Examples
--------
>>> s = load_scenario("paper-14")
>>> s.n, s.N, [s.agent_labels(i) for i in range(s.N)]
(14, 3, [['7'], ['9'], ['12']])
>>> round(s.rho_A, 4)
1.0857
"""

from __future__ import annotations

import csv
import dataclasses
import hashlib
import importlib.resources
import json
import math
import os
import re
import tomllib
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .connectivity import agent_components
from .errors import ScenarioError
from .files import UnreadableFile, read_bounded

__all__ = [
    "Scenario",
    "load_scenario",
    "scenario_from_dict",
    "scenario_to_toml",
    "builtin_scenarios",
    "resolve_delays",
    "uniform_delays",
    "RankDeficientWarning",
    "DeprecatedEdgesHeader",
    "scenario_schema",
    "starter_scenario_toml",
]

def scenario_schema() -> dict:
    """The JSON Schema of a scenario file (``design/scenario.schema.json``, docs/scenario.md).

    The loader takes its key sets and defaults from it; tests check that the schema and
    the loader's own checks agree on every key.

    >>> scenario_schema()["properties"]["agents"]["properties"]["standby"]["default"]
    0
    """
    res = importlib.resources.files("design") / "scenario.schema.json"
    return json.loads(res.read_text())


_SCHEMA = scenario_schema()


def starter_scenario_toml(path: str = "scenario.toml") -> str:
    """The commented starter scenario that ``socmon init`` writes (6 individuals, 2
    agents), its commands naming the file at ``path``.

    >>> s = scenario_from_dict(tomllib.loads(starter_scenario_toml()))
    >>> s.n, s.N, s.standby
    (6, 2, 1)
    >>> "socmon analyze 'my net.toml'" in starter_scenario_toml("my net.toml")
    True
    """
    import shlex

    text = (importlib.resources.files("design") / "scenario_starter.toml").read_text()
    return text.replace("scenario.toml", shlex.quote(str(path)))


def _table_keys(table: str) -> set:
    return set(_SCHEMA["properties"][table]["properties"])


def _default(table: str, key: str):
    """The schema's default of ``[table] key``."""
    return _SCHEMA["properties"][table]["properties"][key]["default"]


_TOP_KEYS = set(_SCHEMA["properties"])
_SOCIAL_KEYS = _table_keys("social")
_AGENT_KEYS = _table_keys("agents")
_NETWORK_KEYS = _table_keys("network")
_RUNTIME_KEYS = _table_keys("runtime")
#: The headers of an edges CSV: row ``i,j`` means i listens to j (``A[i, j] != 0``).
_EDGE_HEADERS = (("listener", "influencer"), ("i", "j"))
#: Headers still read, with a :class:`DeprecatedEdgesHeader` warning: the rows mean what
#: they meant (the first column listens to the second), but the names say the reverse.
_DEPRECATED_EDGE_HEADERS = (("source", "target"),)
_ROW_SUM_TOL = 1e-9
#: Largest link delay, in steps, that a scenario or a delay flag may name. The exact closed
#: loop has order (taubar+1) n N: beyond a thousand steps it is out of reach anyway.
MAX_DELAY = 1000
#: Largest number of individuals of a scenario (A is held dense): labels, rows of A and
#: node ids of an edges file all count. What ``analyze`` costs there: docs/scenario.md.
MAX_NODES = 2000
#: Largest number of active agents (lists of ``agents.measure``; W is held dense).
MAX_AGENTS = 200
#: Largest distributed order n N (every agent holds an estimate of all n individuals; the
#: observability staircase of (W (x) A, D_H) costs about (n N)^3: docs/scenario.md).
MAX_ORDER = 10000
#: Largest number of standby agents a scenario may declare.
MAX_STANDBY = 1000
#: Largest scenario file (tomllib reads about 2.5 MB/s; a dense A of n = 900 is ~15 MiB:
#: larger graphs are given by social.edges).
MAX_SCENARIO_BYTES = 16 << 20
#: Largest edges CSV file (every edge of a complete graph on MAX_NODES nodes fits).
MAX_EDGES_BYTES = 64 << 20
#: Deepest nesting of arrays and inline tables in a scenario file (a scenario needs 2;
#: tomllib recurses on nesting, and a file nested 100 000 deep exhausts Python's stack).
MAX_TOML_DEPTH = 32


class RankDeficientWarning(UserWarning):
    """A is numerically rank deficient (the paper's Assumption 1 fails)."""


class DeprecatedEdgesHeader(FutureWarning):
    """An edges CSV with the header ``source,target``: read as before (the first column
    listens to the second), though an edge source -> target in graph terms says that
    source influences target, the reverse. Rename the header ``listener,influencer`` (or
    ``i,j``); the rows stay as they are."""


@dataclass(frozen=True, eq=False)
class Scenario:
    """One deployment: social dynamics, sensors, agent network, noise and timing.

    Attributes
    ----------
    name : str
    A : ndarray (n, n)
        Social dynamics ``x_{k+1} = A x_k + nu_k``; ``A[i, j] != 0`` means j influences i.
    labels : tuple of str
        Node labels, index i <-> ``labels[i]``.
    process_noise : float
        ``Q = process_noise * I`` (variance).
    measure : tuple of tuple of int
        Node indices (0-based) measured by agents 1..N.
    measurement_noise : float
        ``R_i = measurement_noise * I`` (variance).
    standby : int
        Spare agents available for recovery (ids N+1..N+standby).
    W : ndarray (N, N)
        Row-stochastic fusion weights; ``W[i, j]`` is what agent i+1 gives to agent j+1.
    delays : ndarray of int (N, N)
        ``delays[i, j]`` = delay in steps on link j -> i (0 on the diagonal and off links).
    step_ms : int
        Period of one step in the live runtime.
    source : str
        Where it was read from (file path or ``builtin:NAME``).
    """

    name: str
    A: np.ndarray
    labels: tuple
    process_noise: float
    measure: tuple
    measurement_noise: float
    standby: int
    W: np.ndarray
    delays: np.ndarray
    step_ms: int = 20
    source: str = "<dict>"
    warnings: tuple = field(default=())

    # -- sizes ------------------------------------------------------------------
    @property
    def n(self) -> int:
        """Number of individuals (social nodes)."""
        return self.A.shape[0]

    @property
    def N(self) -> int:
        """Number of active agents."""
        return self.W.shape[0]

    @property
    def taubar(self) -> int:
        """Largest delay on any link of the scenario."""
        return int(self.delays.max()) if self.delays.size else 0

    @property
    def rho_A(self) -> float:
        """Spectral radius of A."""
        return float(np.max(np.abs(np.linalg.eigvals(self.A))))

    @property
    def Q(self) -> np.ndarray:
        return self.process_noise * np.eye(self.n)

    def R(self, i: int) -> np.ndarray:
        """Measurement noise covariance of agent ``i`` (0-based)."""
        return self.measurement_noise * np.eye(len(self.measure[i]))

    # -- sensors ----------------------------------------------------------------
    def H(self, i: int) -> np.ndarray:
        """Canonical measurement matrix ``H_i`` (p_i x n) of agent ``i`` (0-based)."""
        return np.eye(self.n)[list(self.measure[i])]

    @property
    def H_all(self) -> np.ndarray:
        """All agents' measurement rows stacked (p x n)."""
        return np.eye(self.n)[[j for m in self.measure for j in m]]

    @property
    def D_H(self) -> np.ndarray:
        """``blockdiag(H_i^T H_i)`` of order nN."""
        d = np.zeros(self.n * self.N)
        for i, m in enumerate(self.measure):
            d[i * self.n + np.asarray(m, dtype=int)] = 1.0
        return np.diag(d)

    def agent_labels(self, i: int) -> list:
        """Labels of the nodes agent ``i`` (0-based) measures."""
        return [self.labels[j] for j in self.measure[i]]

    def index_of(self, label) -> int:
        """Index of the node with ``label``; ScenarioError if unknown."""
        try:
            return self.labels.index(str(label))
        except ValueError:
            raise ScenarioError(f"unknown node label {label!r}", self.source) from None

    @property
    def neighbours(self) -> list:
        """``neighbours[i]`` = agents j != i (0-based) with ``W[i, j] > 0``."""
        return [
            [j for j in range(self.N) if j != i and self.W[i, j] > 0] for i in range(self.N)
        ]

    # -- identity ---------------------------------------------------------------
    def digest(self) -> str:
        """Hash of everything that determines the estimator (not the name or timing)."""
        h = hashlib.sha256()
        for arr in (self.A, self.W):
            h.update(np.ascontiguousarray(arr, dtype="<f8").tobytes())
        h.update(np.ascontiguousarray(self.delays, dtype="<i8").tobytes())
        h.update(json.dumps([list(map(int, m)) for m in self.measure]).encode())
        h.update(json.dumps([self.process_noise, self.measurement_noise]).encode())
        return h.hexdigest()[:16]

    def replace(self, **changes) -> "Scenario":
        """A copy with ``changes`` applied (validated like a loaded scenario)."""
        new = dataclasses.replace(self, **changes)
        problems = _check_network(new.W, new.delays, "network")
        problems += _check_measure_indices(new.measure, new.n)
        if problems:
            raise ScenarioError(problems, new.source)
        return new

    def to_dict(self) -> dict:
        """JSON-ready summary with 1-based agents and node labels."""
        return {
            "scenario": self.name,
            "n": self.n,
            "N": self.N,
            "labels": list(self.labels),
            "A": self.A.tolist(),
            "W": self.W.tolist(),
            "delays": self.delays.tolist(),
            "measure": [self.agent_labels(i) for i in range(self.N)],
            "process_noise": self.process_noise,
            "measurement_noise": self.measurement_noise,
            "standby": self.standby,
            "step_ms": self.step_ms,
        }


# ---------------------------------------------------------------------------------
# loading


def builtin_scenarios() -> list:
    """Names of the scenarios shipped with socmon."""
    folder = importlib.resources.files("design") / "scenarios"
    return sorted(p.name[:-5] for p in folder.iterdir() if p.name.endswith(".toml"))


def load_scenario(spec) -> Scenario:
    """Load a scenario from a TOML file path or a built-in name.

    Parameters
    ----------
    spec : str or Path
        A path to a ``.toml`` file, or one of :func:`builtin_scenarios`.

    Raises
    ------
    ScenarioError
        Listing every problem found, each naming its field.
    """
    path = Path(spec)
    name = str(spec)
    if name in builtin_scenarios() and not path.is_file():
        res = importlib.resources.files("design") / "scenarios" / f"{name}.toml"
        data = tomllib.loads(res.read_text())
        return scenario_from_dict(data, base_dir=None, source=f"builtin:{name}")
    try:
        raw = read_bounded(path, MAX_SCENARIO_BYTES)
    except UnreadableFile as exc:
        if not os.path.lexists(path):
            raise ScenarioError(
                f"no scenario file {name!r} and no built-in scenario of that name "
                f"(built-in: {', '.join(builtin_scenarios())})"
            ) from None
        raise ScenarioError(f"cannot read the scenario file: {exc}", str(path)) from None
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise ScenarioError(f"not valid TOML: not UTF-8 text ({exc.reason} at byte "
                            f"{exc.start})", str(path)) from None
    data = parse_toml(text, str(path))
    return scenario_from_dict(data, base_dir=path.parent, source=str(path))


def parse_toml(text: str, source: str = "<text>") -> dict:
    """``tomllib.loads(text)`` at a bounded cost: nesting deeper than
    :data:`MAX_TOML_DEPTH` is refused before tomllib, which recurses on it, sees it.

    Raises
    ------
    ScenarioError
        Naming ``source`` (and the line of a too deep nesting) for text that is not TOML.

    >>> parse_toml("a = [[1, 2], [3]]")
    {'a': [[1, 2], [3]]}
    >>> parse_toml("a = " + "[" * 40 + "]" * 40)
    Traceback (most recent call last):
    ...
    design.errors.ScenarioError: <text>: not valid TOML: arrays and inline tables nested deeper than 32 (line 1)
    """
    depth, line = toml_nesting(text, stop=MAX_TOML_DEPTH)
    if depth > MAX_TOML_DEPTH:
        raise ScenarioError(f"not valid TOML: arrays and inline tables nested deeper than "
                            f"{MAX_TOML_DEPTH} (line {line})", source)
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ScenarioError(f"not valid TOML: {exc}", source) from None
    except RecursionError:   # not reached below MAX_TOML_DEPTH; a guard all the same
        raise ScenarioError("not valid TOML: nested too deeply", source) from None


# the TOML tokens that matter to the nesting: strings (brackets in them do not count),
# comments, brackets and braces; then, per opening token, where its string or comment ends
_TOML_TOKEN = re.compile(r'"""|' + r"'''|" + r"""["'#\[\]{}]""")
_TOML_END = {
    '"': re.compile(r'(?:[^"\\\n]|\\.)*"'),
    "'": re.compile(r"[^'\n]*'"),
    '"""': re.compile(r'(?:[^\\]|\\.)*?"""(?:"{1,2}(?!"))?', re.S),
    "'''": re.compile(r".*?'''(?:'{1,2}(?!'))?", re.S),
    "#": re.compile(r"[^\n]*"),
}


def toml_nesting(text: str, stop: int | None = None) -> tuple:
    """``(depth, line)``: the deepest nesting of ``[`` and ``{`` in TOML ``text`` outside
    strings and comments, and the line where it is first reached. Linear in the text and
    without recursion; the scan ends as soon as the depth passes ``stop``. A table header
    ``[[x]]`` counts 2.

    >>> toml_nesting('a = [[1], "[[["]  # [[[[\\nb = {c = [2]}')
    (2, 1)
    >>> toml_nesting("a = '''\\n[[[\\n'''\\nb = [{c = [1]}]")
    (3, 4)
    """
    depth = best = 0
    line = 1
    pos, end = 0, len(text)
    while pos < end:
        m = _TOML_TOKEN.search(text, pos)
        if m is None:
            break
        tok, pos = m.group(), m.end()
        if tok in ("[", "{"):
            depth += 1
            if depth > best:
                best = depth
                line = text.count("\n", 0, m.start()) + 1
                if stop is not None and best > stop:
                    break
        elif tok in ("]", "}"):
            depth = max(depth - 1, 0)
        else:
            s = _TOML_END[tok].match(text, pos)
            if s is None:    # an unterminated string: tomllib reports it
                break
            pos = s.end()
    return best, line


def scenario_to_toml(scenario: Scenario) -> str:
    """The scenario as TOML that :func:`load_scenario` reads back to an equal scenario.

    Everything is written explicitly (A, labels, weights, delays), floats by their
    shortest round-trip repr, so nothing is regenerated from a seed or a topology.

    Examples
    --------
    >>> s = load_scenario("paper-14")
    >>> t = scenario_to_toml(s)
    >>> back = scenario_from_dict(tomllib.loads(t))
    >>> back.digest() == s.digest(), back.labels == s.labels, back.standby == s.standby
    (True, True, True)
    """
    s = scenario

    def num(x) -> str:
        return repr(float(x))

    def string(x) -> str:
        # a JSON string (non-ASCII kept as is) is a TOML basic string, but for DEL
        return json.dumps(str(x), ensure_ascii=False).replace("\x7f", "\\u007f")

    def matrix(M, fmt) -> str:
        return "[\n" + "".join(
            "  [" + ", ".join(fmt(x) for x in row) + "],\n" for row in M) + "]"

    def strings(xs) -> str:
        return "[" + ", ".join(string(x) for x in xs) + "]"

    measure = "[" + ", ".join(strings(s.agent_labels(i)) for i in range(s.N)) + "]"
    source = str(s.source).replace("\n", " ")
    return "\n".join([
        f"# written by socmon from {source}",
        f"name = {string(s.name)}",
        "",
        "[social]",
        f"A = {matrix(s.A, num)}",
        f"labels = {strings(s.labels)}",
        f"process_noise = {num(s.process_noise)}",
        "",
        "[agents]",
        f"measure = {measure}",
        f"measurement_noise = {num(s.measurement_noise)}",
        f"standby = {int(s.standby)}",
        "",
        "[network]",
        f"weights = {matrix(s.W, num)}",
        f"delays = {matrix(s.delays, lambda x: str(int(x)))}",
        "",
        "[runtime]",
        f"step_ms = {int(s.step_ms)}",
        "",
    ])


def scenario_from_dict(data: dict, base_dir=None, source: str = "<dict>") -> Scenario:
    """Build and validate a :class:`Scenario` from the parsed TOML mapping.

    ``base_dir`` resolves a relative ``social.edges`` path.
    """
    problems: list = []
    if not isinstance(data, dict):
        raise ScenarioError("scenario must be a table", source)
    _unknown_keys(data, _TOP_KEYS, "", problems)
    social = _table(data, "social", problems, required=True)
    agents = _table(data, "agents", problems, required=True)
    network = _table(data, "network", problems, required=False)
    runtime = _table(data, "runtime", problems, required=False)
    _unknown_keys(social, _SOCIAL_KEYS, "social.", problems)
    _unknown_keys(agents, _AGENT_KEYS, "agents.", problems)
    _unknown_keys(network, _NETWORK_KEYS, "network.", problems)
    _unknown_keys(runtime, _RUNTIME_KEYS, "runtime.", problems)

    name = data.get("name", Path(source).stem if source else "scenario")
    if not isinstance(name, str) or not name:
        problems.append("name: must be a non-empty string")
        name = "scenario"

    before = len(problems)
    A, labels = _parse_social(social, base_dir, problems)
    social_ok = len(problems) == before   # else its labels are a placeholder: not checked
    q = _positive_number(social, "process_noise", "social.process_noise", problems,
                         _default("social", "process_noise"))
    r = _positive_number(agents, "measurement_noise", "agents.measurement_noise", problems,
                         _default("agents", "measurement_noise"))
    standby = agents.get("standby", _default("agents", "standby"))
    if not _is_int(standby) or not 0 <= standby <= MAX_STANDBY:
        problems.append(
            f"agents.standby: must be a non-negative integer (at most {MAX_STANDBY}), "
            f"got {standby!r}")
        standby = 0
    measure = _parse_measure(agents, labels if social_ok else None, problems)
    N = len(measure) if measure is not None else 0
    W = _parse_weights(network, N, problems) if N else None
    delays = _parse_delays(network, W, problems) if W is not None else None
    step_ms = runtime.get("step_ms", _default("runtime", "step_ms"))
    if not _is_int(step_ms) or step_ms <= 0:
        problems.append(f"runtime.step_ms: must be a positive integer, got {step_ms!r}")
        step_ms = 20

    if problems:
        raise ScenarioError(problems, source)

    notes = []
    rank = np.linalg.matrix_rank(A)
    if rank < A.shape[0]:
        msg = (
            f"social.A: rank {rank} < n = {A.shape[0]}: A is rank deficient "
            "(Assumption 1 fails; structural verdicts may not hold numerically)"
        )
        warnings.warn(f"{source}: {msg}", RankDeficientWarning, stacklevel=2)
        notes.append(msg)
    return Scenario(
        name=name,
        A=A,
        labels=tuple(labels),
        process_noise=float(q),
        measure=tuple(tuple(m) for m in measure),
        measurement_noise=float(r),
        standby=int(standby),
        W=W,
        delays=delays,
        step_ms=int(step_ms),
        source=source,
        warnings=tuple(notes),
    )


# ---------------------------------------------------------------------------------
# delays


def uniform_delays(W: np.ndarray, tau: int) -> np.ndarray:
    """Delay matrix with every inter-agent link of ``W`` delayed by ``tau`` steps."""
    if not _is_int(tau) or tau < 0:
        raise ScenarioError(f"delay: must be a non-negative integer, got {tau!r}")
    if tau > MAX_DELAY:
        raise ScenarioError(f"delay: {tau} steps is above the largest supported, {MAX_DELAY}")
    D = np.where(np.asarray(W) > 0, int(tau), 0).astype(int)
    np.fill_diagonal(D, 0)
    return D


def resolve_delays(scenario: Scenario, spec: str = "scenario") -> np.ndarray:
    """The delay matrix named by ``spec``: ``scenario``, ``none`` or ``uniform:T``.

    >>> s = load_scenario("paper-14")
    >>> resolve_delays(s, "uniform:3")
    array([[0, 3, 0],
           [0, 0, 3],
           [3, 0, 0]])
    """
    spec = str(spec).strip()
    if spec == "scenario":
        return scenario.delays.copy()
    if spec == "none":
        return np.zeros_like(scenario.delays)
    if spec.startswith("uniform:"):
        text = spec.split(":", 1)[1]
        try:
            tau = int(text)
        except ValueError:
            tau = None
        if tau is None or tau < 0 or not text.strip().isascii():
            raise ScenarioError(
                f"--delays: uniform:T needs a non-negative integer T, got {text!r}"
            )
        if tau > MAX_DELAY:
            raise ScenarioError(f"--delays: uniform:{tau} is above the largest delay, {MAX_DELAY}")
        return uniform_delays(scenario.W, tau)
    raise ScenarioError(f"--delays: expected scenario, none or uniform:T, got {spec!r}")


# ---------------------------------------------------------------------------------
# parsing helpers


def _some(items, k: int = 10) -> str:
    """The first ``k`` of ``items`` and how many more (an error message stays short)."""
    items = list(items)
    more = f" and {len(items) - k} more" if len(items) > k else ""
    return f"{items[:k]}{more}"


def _is_int(x) -> bool:
    return isinstance(x, (int, np.integer)) and not isinstance(x, bool)


def _is_number(x) -> bool:
    return isinstance(x, (int, float, np.integer, np.floating)) and not isinstance(x, bool)


def _unknown_keys(table, allowed, prefix, problems):
    if isinstance(table, dict):
        for key in table:
            if key not in allowed:
                problems.append(
                    f"{prefix}{key}: unknown key (allowed: {', '.join(sorted(allowed))})"
                )


def _table(data, key, problems, required):
    value = data.get(key)
    if value is None:
        if required:
            problems.append(f"[{key}]: missing table")
        return {}
    if not isinstance(value, dict):
        problems.append(f"[{key}]: must be a table")
        return {}
    return value


def _positive_number(table, key, where, problems, default):
    value = table.get(key, default)
    if not _is_number(value) or not math.isfinite(value) or value < 0:
        problems.append(f"{where}: must be a finite non-negative number, got {value!r}")
        return default
    return float(value)


def _matrix(value, where, problems, max_rows=None, rows_are="rows"):
    """Parse a list of lists of numbers into a float array, or report why not."""
    if not isinstance(value, list) or not value or not all(isinstance(r, list) for r in value):
        problems.append(f"{where}: must be a non-empty list of rows")
        return None
    if max_rows is not None and len(value) > max_rows:
        problems.append(f"{where}: {len(value)} rows, above the largest supported number of "
                        f"{rows_are}, {max_rows}")
        return None
    widths = {len(r) for r in value}
    if len(widths) != 1:
        problems.append(f"{where}: rows have different lengths {sorted(widths)}")
        return None
    if not all(_is_number(x) for r in value for x in r):
        problems.append(f"{where}: entries must be numbers")
        return None
    M = np.asarray(value, dtype=float)
    if not np.all(np.isfinite(M)):
        bad = np.argwhere(~np.isfinite(M))[0]
        problems.append(f"{where}: non-finite entry at row {bad[0] + 1}, column {bad[1] + 1}")
        return None
    return M


def _parse_social(social, base_dir, problems):
    has_A, has_edges = "A" in social, "edges" in social
    labels = social.get("labels")
    if labels is not None:
        if not isinstance(labels, list) or not all(isinstance(x, (str, int)) for x in labels):
            problems.append("social.labels: must be a list of strings")
            labels = None
        else:
            labels = [str(x) for x in labels]
            if len(labels) > MAX_NODES:
                problems.append(f"social.labels: {len(labels)} labels, above the largest "
                                f"supported number of individuals, {MAX_NODES}")
                return np.eye(1), ["1"]
            seen, dup = set(), set()
            for x in labels:
                (dup if x in seen else seen).add(x)
            if dup:
                problems.append(f"social.labels: duplicate labels {_some(sorted(dup))}")
    if has_A == has_edges:
        problems.append("social: give exactly one of A (dense matrix) or edges (CSV file)")
        return np.eye(1), ["1"]
    if has_A:
        for key in ("self_weight", "seed"):
            if key in social:
                problems.append(f"social.{key}: only meaningful with social.edges")
        A = _matrix(social["A"], "social.A", problems, max_rows=MAX_NODES,
                    rows_are="individuals")
        if A is None:
            return np.eye(1), ["1"]
        if A.shape[0] != A.shape[1]:
            problems.append(f"social.A: must be square, got {A.shape[0]} x {A.shape[1]}")
            return np.eye(1), ["1"]
        transpose = social.get("transpose", _default("social", "transpose"))
        if not isinstance(transpose, bool):
            problems.append("social.transpose: must be true or false")
        elif transpose:
            A = A.T.copy()
    else:
        if "transpose" in social:
            problems.append("social.transpose: only meaningful with social.A")
        A, labels = _edges_matrix(social, base_dir, labels, problems)
        if A is None:
            return np.eye(1), ["1"]
    n = A.shape[0]
    if labels is None:
        labels = [str(i + 1) for i in range(n)]
    elif len(labels) != n:
        problems.append(f"social.labels: {len(labels)} labels for n = {n} nodes")
        labels = [str(i + 1) for i in range(n)]
    if "spectral_radius" in social:
        target = social["spectral_radius"]
        if not _is_number(target) or not math.isfinite(target) or target <= 0:
            problems.append(f"social.spectral_radius: must be a positive number, got {target!r}")
        else:
            rho = float(np.max(np.abs(np.linalg.eigvals(A))))
            if rho == 0:
                problems.append("social.spectral_radius: A is nilpotent (rho = 0), cannot rescale")
            else:
                A = A * (float(target) / rho)
    if not np.all(np.isfinite(A)) or np.abs(A).max() > 1e150:
        problems.append("social.A: entries must be finite and below 1e150 in magnitude "
                        "(after any spectral_radius rescaling)")
        return np.eye(1), ["1"]
    return A, labels


def _edges_matrix(social, base_dir, labels, problems):
    """Read the edges CSV and draw the weights (see the scenario file contract)."""
    rel = social["edges"]
    if not isinstance(rel, str):
        problems.append("social.edges: must be a path string")
        return None, labels
    path = Path(rel)
    if not path.is_absolute() and base_dir is not None:
        path = Path(base_dir) / path
    try:
        lines = read_bounded(path, MAX_EDGES_BYTES).decode("utf-8").splitlines()
    except UnreadableFile as exc:
        problems.append(f"social.edges: cannot read {str(path)!r}: {exc}")
        return None, labels
    except UnicodeDecodeError:
        problems.append(f"social.edges: {str(path)!r} is not UTF-8 text")
        return None, labels
    rows = [r for r in csv.reader(ln for ln in lines if ln.strip() and not ln.lstrip().startswith("#"))]
    if not rows:
        problems.append(f"social.edges: {path} has no header and no rows")
        return None, labels
    header = tuple(c.strip().lower() for c in rows[0][:2])
    if header in _DEPRECATED_EDGE_HEADERS:
        warnings.warn(
            f"social.edges: {path}: the header {','.join(header)} is deprecated: its rows "
            "are read as before (row 'i,j': i listens to j, j influences i), which is the "
            "reverse of what source,target says of an edge; rename the header "
            "listener,influencer (or i,j), the rows stay as they are",
            DeprecatedEdgesHeader, stacklevel=2)
    elif header not in _EDGE_HEADERS:
        problems.append(
            f"social.edges: {path}: bad header {rows[0]!r}; the first two columns must be "
            "named listener,influencer (or i,j): row 'i,j' means i listens to j"
        )
        return None, labels
    pairs = []
    for lineno, row in enumerate(rows[1:], start=2):
        if len(row) < 2 or not row[0].strip() or not row[1].strip():
            problems.append(f"social.edges: {path} data row {lineno}: needs two ids, got {row!r}")
            continue
        pairs.append((row[0].strip(), row[1].strip()))
    if not pairs:
        problems.append(f"social.edges: {path} has no edges")
        return None, labels
    ids = sorted({x for p in pairs for x in p})
    if labels is None:
        if all(x.isascii() and x.isdigit() and int(x) >= 1 for x in ids):
            top = max(int(x) for x in ids)
            if top > MAX_NODES:
                problems.append(f"social.edges: {path}: node id {top} is above the largest "
                                f"supported, {MAX_NODES} (give social.labels for sparse ids)")
                return None, labels
            labels = [str(i + 1) for i in range(top)]
            canon = {x: str(int(x)) for x in ids}
        else:
            if len(ids) > MAX_NODES:
                problems.append(f"social.edges: {path}: {len(ids)} node ids, above the largest "
                                f"supported number of individuals, {MAX_NODES}")
                return None, labels
            labels = ids
            canon = {x: x for x in ids}
    else:
        canon = {x: x for x in ids}
    index = {lab: i for i, lab in enumerate(labels)}
    unknown = sorted({x for x in ids if canon[x] not in index})
    if unknown:
        problems.append(f"social.edges: {path}: ids not among social.labels: {_some(unknown)}")
        return None, labels
    n = len(labels)
    mask = np.zeros((n, n), dtype=bool)
    for a, b in pairs:
        mask[index[canon[a]], index[canon[b]]] = True
    self_weight = social.get("self_weight", _default("social", "self_weight"))
    if not isinstance(self_weight, bool):
        problems.append("social.self_weight: must be true or false")
        self_weight = True
    if self_weight:
        np.fill_diagonal(mask, True)
    seed = social.get("seed", _default("social", "seed"))
    if not _is_int(seed) or seed < 0:
        problems.append(f"social.seed: must be a non-negative integer, got {seed!r}")
        seed = 0
    rng = np.random.default_rng(int(seed))
    A = np.zeros((n, n))
    A[mask] = rng.uniform(0.1, 1.0, size=int(mask.sum()))
    return A, labels


def _parse_measure(agents, labels, problems):
    measure = agents.get("measure")
    if not isinstance(measure, list) or not measure:
        problems.append("agents.measure: must be a non-empty list of lists of node labels")
        return None
    if len(measure) > MAX_AGENTS:
        problems.append(f"agents.measure: {len(measure)} agents, above the largest supported "
                        f"number, {MAX_AGENTS}")
        return None
    if labels is not None and len(labels) * len(measure) > MAX_ORDER:
        problems.append(
            f"agents.measure: {len(measure)} agents estimating n = {len(labels)} individuals "
            f"each: the distributed order n N = {len(labels) * len(measure)} is above the "
            f"largest supported, {MAX_ORDER}")
        return None
    index = {lab: i for i, lab in enumerate(labels)} if labels is not None else None
    out = []
    for a, group in enumerate(measure, start=1):
        where = _agent_field(a)
        if not isinstance(group, list) or not group:
            problems.append(f"{where}: agent {a} must measure a non-empty list of labels")
            out.append(())
            continue
        idx, unknown = [], []
        for lab in group:
            if index is None:
                idx.append(str(lab))      # the graph's labels are unknown: only the shape
            elif str(lab) not in index:
                unknown.append(lab)
            else:
                idx.append(index[str(lab)])
        for lab in unknown[:3]:
            problems.append(f"{where}: unknown node label {lab!r}")
        if len(unknown) > 3:
            problems.append(f"{where}: and {len(unknown) - 3} more unknown labels")
        twice = sorted({str(lab) for lab in group if [str(x) for x in group].count(str(lab)) > 1})
        if twice:
            problems.append(f"{where}: agent {a} lists {', '.join(map(repr, twice))} twice")
        out.append(tuple(idx))
    return out


def _shape_words(raw) -> str:
    """What a value meant as a matrix is, in words.

    >>> _shape_words([[0, 1], [2]]), _shape_words([[0, 1, 2]] * 3), _shape_words(5)
    ('rows of lengths 2, 1', '3 x 3', 'a int')
    """
    if not isinstance(raw, list):
        return f"a {type(raw).__name__}"
    if not all(isinstance(r, list) for r in raw):
        return "a list whose rows are not all lists"
    lengths = {len(r) for r in raw}
    if len(lengths) > 1:
        return "rows of lengths " + ", ".join(str(len(r)) for r in raw[:8])
    return f"{len(raw)} x {lengths.pop() if lengths else 0}"


def _agent_field(a: int) -> str:
    """The field of agent ``a``'s sensors (1-based id; the list's index is a - 1).

    >>> _agent_field(2)
    'agents.measure[1] (agent 2)'
    """
    return f"agents.measure[{a - 1}] (agent {a})"


def _parse_weights(network, N, problems):
    where = "network"
    if "weights" in network:
        for key in ("topology", "self_weight"):
            if key in network:
                problems.append(f"network.{key}: give either weights or topology/self_weight")
        raw = network["weights"]
        if isinstance(raw, list) and len(raw) != N:
            cols = len(raw[0]) if raw and isinstance(raw[0], list) else 0
            problems.append(f"network.weights: must be {N} x {N} (one row per agent in "
                            f"agents.measure), got {len(raw)} x {cols}")
            return None
        W = _matrix(raw, "network.weights", problems)
        if W is None:
            return None
        if W.shape != (N, N):
            problems.append(
                f"network.weights: must be {N} x {N} (one row per agent in agents.measure), "
                f"got {W.shape[0]} x {W.shape[1]}"
            )
            return None
    else:
        topology = network.get("topology", _default("network", "topology"))
        sw = network.get("self_weight", _default("network", "self_weight"))
        if not _is_number(sw) or not 0 < sw <= 1:
            problems.append(f"network.self_weight: must be in (0, 1], got {sw!r}")
            return None
        W = np.zeros((N, N))
        if N == 1:
            W[0, 0] = 1.0
        elif topology == "cycle":
            # agent i listens to agent i+1: information flows N -> ... -> 2 -> 1 -> N
            for i in range(N):
                W[i, i] = sw
                W[i, (i + 1) % N] = 1.0 - sw
        elif topology == "complete":
            W[:] = (1.0 - sw) / (N - 1)
            np.fill_diagonal(W, sw)
        else:
            problems.append(f"network.topology: expected 'cycle' or 'complete', got {topology!r}")
            return None
        if sw == 1 and N > 1:
            problems.append("network.self_weight: 1 leaves no weight for neighbours")
    problems.extend(_check_weights(W, where))
    return W


def _check_weights(W, where):
    problems = []
    if np.any(W < 0):
        i, j = np.argwhere(W < 0)[0]
        problems.append(f"{where}.weights: negative weight at agent {i + 1}, neighbour {j + 1}")
    sums = W.sum(axis=1)
    bad = np.flatnonzero(np.abs(sums - 1.0) > _ROW_SUM_TOL)
    if bad.size:
        problems.append(
            f"{where}.weights: not row-stochastic: rows of agents "
            f"{[int(i) + 1 for i in bad]} sum to {[round(float(sums[i]), 12) for i in bad]}"
        )
    zero_self = np.flatnonzero(np.diag(W) <= 0)
    if zero_self.size:
        problems.append(
            f"{where}.weights: zero self weight w_ii for agents {[int(i) + 1 for i in zero_self]}"
        )
    comps = agent_components(W)
    if len(comps) > 1:
        problems.append(
            f"{where}: agent graph G_W is not strongly connected; its components are "
            f"{[[a + 1 for a in c] for c in comps]}"
        )
    return problems


def _parse_delays(network, W, problems):
    N = W.shape[0]
    has_matrix = "delays" in network
    has_random = "max_delay" in network or "delay_seed" in network
    if has_matrix and has_random:
        problems.append("network: give either delays or max_delay/delay_seed, not both")
        return np.zeros((N, N), dtype=int)
    if has_matrix:
        raw = network["delays"]
        if (
            not isinstance(raw, list)
            or not all(isinstance(r, list) for r in raw)
            or len(raw) != N
            or any(len(r) != N for r in raw)
        ):
            problems.append(f"network.delays: must be a {N} x {N} matrix of integers, got "
                            + _shape_words(raw))
            return np.zeros((N, N), dtype=int)
        if not all(_is_int(x) for r in raw for x in r):
            bad = [x for r in raw for x in r if not _is_int(x)]
            problems.append(f"network.delays: entries must be integers (steps), got {bad[0]!r}")
            return np.zeros((N, N), dtype=int)
        huge = [x for r in raw for x in r if abs(x) > MAX_DELAY]
        if huge:
            problems.append(f"network.delays: delay {huge[0]} is outside -{MAX_DELAY}..{MAX_DELAY}")
            return np.zeros((N, N), dtype=int)
        D = np.asarray(raw, dtype=int)
    elif has_random:
        tmax = network.get("max_delay", _default("network", "max_delay"))
        seed = network.get("delay_seed", _default("network", "delay_seed"))
        if not _is_int(tmax) or not 0 <= tmax <= MAX_DELAY:
            problems.append(
                f"network.max_delay: must be a non-negative integer (at most {MAX_DELAY}), "
                f"got {tmax!r}")
            return np.zeros((N, N), dtype=int)
        if not _is_int(seed) or seed < 0:
            problems.append(f"network.delay_seed: must be a non-negative integer, got {seed!r}")
            return np.zeros((N, N), dtype=int)
        rng = np.random.default_rng(int(seed))
        D = np.where(W > 0, rng.integers(0, int(tmax) + 1, size=W.shape), 0)
        np.fill_diagonal(D, 0)
        return D.astype(int)
    else:
        return np.zeros((N, N), dtype=int)
    problems.extend(_check_delays(D, W, "network.delays"))
    return D


def _check_delays(D, W, where):
    problems = []
    if np.any(D < 0):
        i, j = np.argwhere(D < 0)[0]
        problems.append(f"{where}: negative delay {D[i, j]} on link {j + 1} -> {i + 1}")
    if np.any(D > MAX_DELAY):
        i, j = np.argwhere(D > MAX_DELAY)[0]
        problems.append(f"{where}: delay {D[i, j]} on link {j + 1} -> {i + 1} is above the "
                        f"largest supported, {MAX_DELAY}")
    off = (D != 0) & ~(W > 0)
    if np.any(off):
        i, j = np.argwhere(off)[0]
        problems.append(
            f"{where}: delay {D[i, j]} on link {j + 1} -> {i + 1}, which is not a link of W"
        )
    if np.any(np.diag(D) != 0):
        i = int(np.flatnonzero(np.diag(D) != 0)[0])
        problems.append(f"{where}: self link of agent {i + 1} must have delay 0")
    return problems


def _check_network(W, delays, where):
    W = np.asarray(W, dtype=float)
    delays = np.asarray(delays)
    if W.ndim != 2 or W.shape[0] != W.shape[1]:
        return [f"{where}.weights: must be square, got shape {W.shape}"]
    if delays.shape != W.shape:
        return [f"{where}.delays: shape {delays.shape} does not match W {W.shape}"]
    return _check_weights(W, where) + _check_delays(delays, W, f"{where}.delays")


def _check_measure_indices(measure, n):
    problems = []
    for a, m in enumerate(measure, start=1):
        if not m:
            problems.append(f"{_agent_field(a)}: agent {a} measures nothing")
        for j in m:
            if not 0 <= int(j) < n:
                problems.append(f"{_agent_field(a)}: node index {j} out of range")
    return problems

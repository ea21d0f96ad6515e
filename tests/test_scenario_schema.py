"""The scenario's JSON Schema, its loader, its documentation and ``socmon init`` agree.

The schema (design/scenario.schema.json) uses a small subset of JSON Schema 2020-12;
``_schema_errors`` below implements exactly that subset (a test checks that no other
keyword appears), so that every key's type, range, default and exclusions can be checked
against the loader's own verdicts without a further dependency.
"""

import copy
import json
import re
import tomllib
from pathlib import Path

import numpy as np
import pytest

from agent.cli.main import main
from design.errors import ScenarioError
from design.scenario import (
    MAX_DELAY,
    MAX_STANDBY,
    builtin_scenarios,
    load_scenario,
    scenario_from_dict,
    scenario_schema,
    starter_scenario_toml,
)

ROOT = Path(__file__).resolve().parents[1]
SCHEMA = scenario_schema()
_ASSERTIONS = {"type", "enum", "minimum", "maximum", "exclusiveMinimum", "minItems",
               "minLength", "items", "properties", "additionalProperties", "required",
               "oneOf", "allOf", "anyOf", "not"}
_ANNOTATIONS = {"$schema", "$id", "title", "description", "default"}


def _is_type(value, name) -> bool:
    return {
        "object": isinstance(value, dict),
        "array": isinstance(value, list),
        "string": isinstance(value, str),
        "boolean": isinstance(value, bool),
        "integer": isinstance(value, int) and not isinstance(value, bool),
        "number": isinstance(value, (int, float)) and not isinstance(value, bool),
    }[name]


def _schema_errors(value, schema, path="") -> list:
    """Paths where ``value`` violates ``schema`` (the subset of keywords in _ASSERTIONS)."""
    errors = []
    if "type" in schema:
        types = schema["type"] if isinstance(schema["type"], list) else [schema["type"]]
        if not any(_is_type(value, t) for t in types):
            return [path]
    if "enum" in schema and value not in schema["enum"]:
        errors.append(path)
    if _is_type(value, "number"):
        if "minimum" in schema and value < schema["minimum"]:
            errors.append(path)
        if "maximum" in schema and value > schema["maximum"]:
            errors.append(path)
        if "exclusiveMinimum" in schema and value <= schema["exclusiveMinimum"]:
            errors.append(path)
    if isinstance(value, str) and len(value) < schema.get("minLength", 0):
        errors.append(path)
    if isinstance(value, list):
        if len(value) < schema.get("minItems", 0):
            errors.append(path)
        if "items" in schema:
            for i, item in enumerate(value):
                errors += _schema_errors(item, schema["items"], f"{path}[{i}]")
    if isinstance(value, dict):
        props = schema.get("properties", {})
        for key, item in value.items():
            where = f"{path}.{key}" if path else key
            if key in props:
                errors += _schema_errors(item, props[key], where)
            elif schema.get("additionalProperties") is False:
                errors.append(where)
        errors += [path or "<top>"] * sum(k not in value for k in schema.get("required", []))
    for sub in schema.get("allOf", []):
        errors += _schema_errors(value, sub, path)
    if "anyOf" in schema and all(_schema_errors(value, s, path) for s in schema["anyOf"]):
        errors.append(path)
    if "oneOf" in schema and sum(not _schema_errors(value, s, path)
                                 for s in schema["oneOf"]) != 1:
        errors.append(path)
    if "not" in schema and not _schema_errors(value, schema["not"], path):
        errors.append(path)
    return errors


def _keywords(schema, found=None) -> set:
    found = set() if found is None else found
    if isinstance(schema, dict):
        for key, value in schema.items():
            found.add(key)
            if key == "properties":
                for sub in value.values():
                    _keywords(sub, found)
            elif key in ("items", "not"):
                _keywords(value, found)
            elif key in ("allOf", "anyOf", "oneOf"):
                for sub in value:
                    _keywords(sub, found)
    return found


def test_schema_uses_only_the_checked_keywords():
    assert _keywords(SCHEMA) <= _ASSERTIONS | _ANNOTATIONS, _keywords(SCHEMA) - _ASSERTIONS


def test_schema_limits_are_the_loaders():
    props = SCHEMA["properties"]
    assert props["agents"]["properties"]["standby"]["maximum"] == MAX_STANDBY
    assert props["network"]["properties"]["max_delay"]["maximum"] == MAX_DELAY
    assert props["network"]["properties"]["delays"]["items"]["items"]["maximum"] == MAX_DELAY


# -- the base scenarios the cases are made from -------------------------------------------

A6 = [[0.5, 0.3, 0, 0, 0.2, 0], [0.3, 0.6, 0, 0, 0, 0], [0, 0, 0.6, 0.2, 0, 0.2],
      [0, 0, 0.5, 0.4, 0, 0], [0, 0, 0, 0, 0.5, 0.4], [0, 0, 0, 0, 0.3, 0.6]]


def _dense():
    return {"name": "t", "social": {"A": copy.deepcopy(A6), "transpose": False,
                                    "spectral_radius": 0.9, "process_noise": 0.05,
                                    "labels": ["a", "b", "c", "d", "e", "f"]},
            "agents": {"measure": [["b"], ["d"]], "measurement_noise": 0.05, "standby": 1},
            "network": {"topology": "complete", "self_weight": 0.6, "max_delay": 2,
                        "delay_seed": 1},
            "runtime": {"step_ms": 20}}


def _explicit():
    d = _dense()
    d["network"] = {"weights": [[0.6, 0.4], [0.3, 0.7]], "delays": [[0, 2], [1, 0]]}
    return d


def _edges(tmp_path):
    csv = tmp_path / "e.csv"
    csv.write_text("i,j\n1,2\n2,1\n1,5\n3,4\n4,3\n3,6\n5,6\n6,5\n")
    d = _dense()
    d["social"] = {"edges": csv.name, "self_weight": True, "seed": 3, "process_noise": 0.05}
    d["agents"]["measure"] = [[2], [4]]
    return d


def _bases(tmp_path):
    return {"dense": _dense(), "explicit": _explicit(), "edges": _edges(tmp_path)}


def _loader_problems(data, tmp_path) -> list:
    try:
        scenario_from_dict(data, base_dir=tmp_path)
    except ScenarioError as exc:
        return list(exc.problems) if hasattr(exc, "problems") else [str(exc)]
    return []


def _wrong_values(schema) -> list:
    """Values that ``schema`` (one key's) rejects: other types, out of range, not in enum."""
    types = schema.get("type", [])
    types = types if isinstance(types, list) else [types]
    candidates = ["x", "", True, 1.5, -1, {"a": 1}, [], [[]], [["x"]], [[-1]], [[1.5]]]
    wrong = [v for v in candidates if _schema_errors(v, schema)]
    for bound in ("minimum", "exclusiveMinimum"):
        if bound in schema:
            wrong.append(schema[bound] - (1 if "integer" in types else 0.5)
                         if bound == "minimum" else schema[bound])
    if "maximum" in schema:
        wrong.append(schema["maximum"] + 1)
    if "enum" in schema:
        wrong.append("other")
    assert all(_schema_errors(v, schema) for v in wrong)
    return wrong


def _cases():
    """(base, table, key) for every key of the schema, on a base where it is allowed."""
    out = [("dense", None, "name")]
    for table, spec in SCHEMA["properties"].items():
        if "properties" not in spec:
            continue
        for key in spec["properties"]:
            if table == "social" and key in ("edges", "self_weight", "seed"):
                base = "edges"
            elif table == "network" and key in ("weights", "delays"):
                base = "explicit"
            else:
                base = "dense"
            out.append((base, table, key))
    return out


def test_the_bases_are_valid_for_both(tmp_path):
    for name, data in _bases(tmp_path).items():
        assert _schema_errors(data, SCHEMA) == [], name
        assert _loader_problems(data, tmp_path) == [], name


@pytest.mark.parametrize("base, table, key", _cases())
def test_every_wrong_value_is_refused_by_both_naming_the_key(tmp_path, base, table, key):
    data = _bases(tmp_path)[base]
    spec = SCHEMA["properties"][key] if table is None else \
        SCHEMA["properties"][table]["properties"][key]
    field = key if table is None else f"{table}.{key}"
    for value in _wrong_values(spec):
        bad = copy.deepcopy(data)
        (bad if table is None else bad[table])[key] = value
        assert _schema_errors(bad, SCHEMA), (field, value)
        problems = _loader_problems(bad, tmp_path)
        assert any(p.startswith(field) for p in problems), (field, value, problems)


@pytest.mark.parametrize("table", [None, "social", "agents", "network", "runtime"])
def test_unknown_keys_are_refused_by_both(tmp_path, table):
    bad = _dense()
    (bad if table is None else bad[table])["colour"] = 1
    assert _schema_errors(bad, SCHEMA)
    field = "colour" if table is None else f"{table}.colour"
    assert any(p.startswith(f"{field}: unknown key") for p in _loader_problems(bad, tmp_path))


@pytest.mark.parametrize("table, keys", [
    ("social", {"A": A6, "edges": "e.csv"}),                      # exactly one of A, edges
    ("social", {"A": A6, "seed": 1}),                             # seed only with edges
    ("social", {"edges": "e.csv", "transpose": True}),            # transpose only with A
    ("network", {"weights": [[0.6, 0.4], [0.3, 0.7]], "topology": "cycle"}),
    ("network", {"weights": [[0.6, 0.4], [0.3, 0.7]], "self_weight": 0.5}),
    ("network", {"delays": [[0, 1], [1, 0]], "max_delay": 2}),
    ("network", {"delays": [[0, 1], [1, 0]], "delay_seed": 2}),
])
def test_exclusive_keys_are_refused_by_both(tmp_path, table, keys):
    bad = _edges(tmp_path) if "edges" in keys else _dense()
    bad[table] = {k: v for k, v in bad[table].items()
                  if k not in ("A", "edges", "transpose", "self_weight", "seed",
                               "topology", "max_delay", "delay_seed")}
    bad[table].update(copy.deepcopy(keys))
    assert _schema_errors(bad, SCHEMA), keys
    assert _loader_problems(bad, tmp_path), keys
    bad[table].pop(list(keys)[-1])           # without the second key, both accept
    assert not _schema_errors(bad, SCHEMA), keys
    assert not _loader_problems(bad, tmp_path), keys


def test_missing_required_refused_by_both(tmp_path):
    for table, key in (("social", "A"), ("agents", "measure")):
        bad = _dense()
        del bad[table][key]
        assert _schema_errors(bad, SCHEMA) and _loader_problems(bad, tmp_path)
    for table in ("social", "agents"):
        bad = _dense()
        del bad[table]
        assert _schema_errors(bad, SCHEMA)
        assert f"[{table}]: missing table" in _loader_problems(bad, tmp_path)


def test_defaults_are_the_loaders():
    minimal = {"social": {"A": A6}, "agents": {"measure": [["2"], ["4"]]}}
    s = scenario_from_dict(minimal)
    props = {t: SCHEMA["properties"][t]["properties"] for t in ("social", "agents",
                                                                 "network", "runtime")}
    assert s.process_noise == props["social"]["process_noise"]["default"]
    assert s.measurement_noise == props["agents"]["measurement_noise"]["default"]
    assert s.standby == props["agents"]["standby"]["default"]
    assert s.step_ms == props["runtime"]["step_ms"]["default"]
    assert props["network"]["topology"]["default"] == "cycle"
    sw = props["network"]["self_weight"]["default"]
    assert np.array_equal(s.W, [[sw, 1 - sw], [1 - sw, sw]])
    assert not s.delays.any() and props["network"]["max_delay"]["default"] == 0
    assert props["social"]["transpose"]["default"] is False
    assert s.labels == tuple(str(i) for i in range(1, 7))


def test_builtin_and_starter_scenarios_validate():
    folder = ROOT / "design" / "scenarios"
    for name in builtin_scenarios():
        data = tomllib.loads((folder / f"{name}.toml").read_text())
        assert _schema_errors(data, SCHEMA) == [], name
    assert _schema_errors(tomllib.loads(starter_scenario_toml()), SCHEMA) == []


def test_delays_direction_is_link_j_to_i():
    d = _explicit()
    d["network"]["delays"] = [[0, 2], [1, 0]]
    s = scenario_from_dict(d)
    assert s.delays[0, 1] == 2           # agent 2 -> agent 1 takes 2 steps
    d["network"]["weights"] = [[1.0, 0.0], [0.3, 0.7]]   # agent 1 no longer hears agent 2
    with pytest.raises(ScenarioError, match=r"delay 2 on link 2 -> 1, which is not a link"):
        scenario_from_dict(d)


# -- socmon init and the documentation -----------------------------------------------------

def test_init_writes_a_scenario_that_runs(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    assert main(["init"]) == 0
    assert main(["init"]) == 2
    assert "exists (--force to overwrite)" in capsys.readouterr().err
    s = load_scenario(tmp_path / "scenario.toml")
    assert (s.n, s.N, s.standby) == (6, 2, 1)
    assert main(["analyze", "scenario.toml", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["distributed_observable"] and out["failure_tolerance"] >= 1
    assert main(["design", "scenario.toml", "--objective", "mse", "--out", "g.npz",
                 "--max-iter", "60"]) == 0
    capsys.readouterr()
    assert main(["simulate", "scenario.toml", "--gains", "g.npz", "--trials", "3",
                 "--steps", "60", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert np.isfinite(out["mse_steady"]) and not out["diverged"]


def test_init_schema_file_is_named_for_editors(tmp_path, capsys):
    path, schema = tmp_path / "s.toml", tmp_path / "schema" / "scenario.schema.json"
    schema.parent.mkdir()
    assert main(["init", str(path), "--schema", str(schema)]) == 0
    assert path.read_text().splitlines()[0] == "#:schema schema/scenario.schema.json"
    assert json.loads(schema.read_text()) == SCHEMA
    load_scenario(path)
    assert main(["init", str(tmp_path / "x.toml"), "--schema", str(tmp_path / "no" / "s.json")]) == 2
    assert "--schema: no directory" in capsys.readouterr().err


def _doc_toml_blocks() -> list:
    text = (ROOT / "docs" / "scenario.md").read_text()
    return re.findall(r"```toml\n(.*?)```", text, flags=re.S)


def test_the_documented_example_loads_as_described():
    (block,) = _doc_toml_blocks()
    s = scenario_from_dict(tomllib.loads(block))
    assert s.name == "two-pairs" and s.labels == ("ann", "bob", "cy", "dee", "eve", "fay")
    assert [s.agent_labels(i) for i in range(s.N)] == [["bob"], ["dee"]]
    assert s.delays.tolist() == [[0, 2], [1, 0]] and s.W[0, 0] == 0.6
    from design.analysis import structural_analysis
    st = structural_analysis(s.A)
    parents = {frozenset(s.labels[v] for v in st.structure.components[c]) for c in st.parents}
    assert parents == {frozenset({"ann", "bob"}), frozenset({"cy", "dee"})}


def test_the_documented_keys_are_the_schemas():
    """Every key of the schema has a row in docs/scenario.md, and no other key does."""
    text = (ROOT / "docs" / "scenario.md").read_text()
    documented = set()
    for section, table in re.findall(r"### (`\[\w+\]`[^\n]*|Top level)\n(.*?)(?=\n### |\n## )",
                                     text, flags=re.S):
        name = "" if section == "Top level" else re.match(r"`\[(\w+)\]`", section).group(1)
        for key in re.findall(r"^\| `([\w\[\]]+)` \|", table, flags=re.M):
            if not key.startswith("["):
                documented.add(f"{name}.{key}" if name else key)
    expected = {"name"} | {f"{t}.{k}" for t, spec in SCHEMA["properties"].items()
                           if "properties" in spec for k in spec["properties"]}
    assert documented == expected


def test_a_scenario_written_from_the_doc_runs(tmp_path, capsys):
    """Six individuals from a CSV with names, two agents with explicit weights and drawn
    delays, written from docs/scenario.md alone."""
    (tmp_path / "village.csv").write_text(
        "listener,influencer\n# row i,j: i listens to j\namy,ben\nben,amy\nben,eli\ncal,dan\n"
        "dan,cal\ndan,fox\neli,fox\nfox,eli\n")
    path = tmp_path / "village.toml"
    path.write_text('name = "village"\n[social]\nedges = "village.csv"\nseed = 4\n'
                    'spectral_radius = 0.95\n[agents]\nmeasure = [["amy"], ["cal"]]\n'
                    'standby = 1\n[network]\nweights = [[0.7, 0.3], [0.4, 0.6]]\n'
                    'max_delay = 3\ndelay_seed = 2\n')
    s = load_scenario(path)
    assert s.labels == ("amy", "ben", "cal", "dan", "eli", "fox")
    assert s.A[0, 1] != 0 and s.A[1, 0] != 0 and s.A[0, 2] == 0   # amy listens to ben
    assert abs(s.rho_A - 0.95) < 1e-12 and s.taubar <= 3
    assert main(["analyze", str(path), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["distributed_observable"]
    g = tmp_path / "g.npz"
    assert main(["design", str(path), "--objective", "mse", "--out", str(g),
                 "--max-iter", "60"]) == 0
    capsys.readouterr()
    assert main(["simulate", str(path), "--gains", str(g), "--trials", "3", "--steps", "60",
                 "--json"]) == 0
    assert not json.loads(capsys.readouterr().out)["diverged"]


def test_the_starter_designs_without_numerical_warnings():
    """Its loop has exact eigenvalues where the radius gradient's inverse iteration shifts
    (a singular shift): handled without LinAlgWarning or invalid-value warnings."""
    import warnings

    from design.gain_design import design_gains

    s = scenario_from_dict(tomllib.loads(starter_scenario_toml()))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        result = design_gains(s, max_iter=60)
    assert result.stable

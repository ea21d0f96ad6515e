"""One JSON vocabulary (docs/json.md): every command's ``--json`` carries ``schema_version``,
names the scenario ``scenario``, gives ``delays`` as a matrix, and no former key survives."""

import json
import re
from pathlib import Path

import numpy as np
import pytest

from agent.cli.main import main
from agent.run.jsonable import SCHEMA_VERSION
from design.gains import gains_meta, save_gains

ROOT = Path(__file__).resolve().parents[1]
FORMER = ("rho_scenario_delays", "stable_scenario_delays", "mse_steady_scenario_delays",
          "rho_closed_loop", "mse_steady_predicted", "rho_after", "mse_steady_exact_after",
          "mse_steady_sim")


def _keys(obj, out=None) -> set:
    out = set() if out is None else out
    if isinstance(obj, dict):
        for k, v in obj.items():
            out.add(k)
            _keys(v, out)
    elif isinstance(obj, list):
        for v in obj:
            _keys(v, out)
    return out


def _delays_values(obj):
    if isinstance(obj, dict):
        for k, v in obj.items():
            if k == "delays":
                yield v
            else:
                yield from _delays_values(v)
    elif isinstance(obj, list):
        for v in obj:
            yield from _delays_values(v)


@pytest.fixture(scope="module")
def gains14(paper14, paper14_design, tmp_path_factory):
    res = paper14_design
    path = tmp_path_factory.mktemp("g") / "g.npz"
    save_gains(path, res.G, gains_meta(paper14, "default", res.delays, res.rho,
                                        mse_steady_exact=res.mse_steady))
    return str(path)


def _commands(gains, tmp):
    return {
        "analyze": ["analyze", "paper-14"],
        "plan": ["plan", "paper-14", "--fail", "1"],
        "certify": ["certify", "paper-14", "--gains", gains, "--taus", "0,2"],
        "design": ["design", "paper-14", "--max-iter", "10", "--starts", "1",
                   "--out", str(tmp / "d.npz")],
        "simulate": ["simulate", "paper-14", "--gains", gains, "--steps", "40",
                     "--trials", "2", "--fail", "20:1", "--recover"],
    }


@pytest.mark.parametrize("name", ["analyze", "plan", "certify", "design",
                                  pytest.param("simulate", marks=pytest.mark.slow)])
def test_every_json_output_speaks_the_glossary(name, gains14, tmp_path, capsys):
    command = _commands(gains14, tmp_path)[name]
    assert main(command + ["--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert next(iter(out)) == "schema_version" and out["schema_version"] == SCHEMA_VERSION
    keys = _keys(out)
    assert not keys & set(FORMER), keys & set(FORMER)
    assert "name" not in out and out["scenario"] == "paper-14"
    for value in _delays_values(out):
        assert isinstance(value, list) and all(isinstance(r, list) for r in value), value
        assert np.asarray(value).dtype.kind == "i"


def test_certify_reports_the_exact_mse_at_every_delay(gains14, capsys):
    assert main(["certify", "paper-14", "--gains", gains14, "--taus", "0,1,2", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    rows = out["rows"]
    assert [r["tau"] for r in rows] == [0, 1, 2]
    assert rows[0]["mse_steady_exact"] == pytest.approx(out["mse_steady_delay_free"])
    for r in rows:
        assert (r["mse_steady_exact"] is None) == (not r["stable"])


def test_no_former_key_is_left_in_sources_scripts_or_docs():
    pattern = re.compile(r"[\"'`](%s)[\"'`\]]" % "|".join(FORMER))
    hits = []
    for folder in ("agent", "design", "broker_free_net", "scripts", "docs", "tests"):
        for path in (ROOT / folder).rglob("*"):
            if path.suffix not in (".py", ".md") or path.name == "test_json_vocabulary.py":
                continue
            text = path.read_text()
            if path.name == "json.md":          # the table of former names
                text = text.split("## Former names")[0]
            hits += [f"{path.relative_to(ROOT)}: {m.group(1)}" for m in pattern.finditer(text)]
    assert hits == []

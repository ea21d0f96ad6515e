"""docker/ checked without a Docker engine (scripts/check_docker.py), and its checks fail
on broken files."""

import importlib.util
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
spec = importlib.util.spec_from_file_location("check_docker", ROOT / "scripts" / "check_docker.py")
check_docker = importlib.util.module_from_spec(spec)
sys.modules["check_docker"] = check_docker
spec.loader.exec_module(check_docker)

ENV = {"SOCMON_STEPS": "1234", "SOCMON_RUN": "r", "BASE": "python:3.12-slim"}


def test_the_docker_files_pass_every_check_without_an_engine():
    problems = []
    services = check_docker.check_compose(problems, ENV)
    sources = check_docker.check_dockerfile(problems)
    check_docker.check_ignore(check_docker.read_ignore(), sources, problems)
    assert problems == []
    assert set(check_docker.SERVICES) <= set(services)
    assert sources == ["pyproject.toml", "README.md", "design", "agent", "broker_free_net"]


def test_the_build_context_holds_the_sources_only():
    files = list(check_docker.context_files(ROOT, check_docker.read_ignore()))
    assert "agent/cli/main.py" in files and "pyproject.toml" in files
    assert not [f for f in files if f.startswith((".venv/", ".git/", "runs/", "tests/"))
                or "__pycache__" in f]


@pytest.mark.parametrize("pattern, path, ignored", [
    (".venv", ".venv/bin/python", True), ("**/runs", "a/b/runs/x.json", True),
    ("runs", "design/runs/x", False), ("*.npz", "g.npz", True), ("*.npz", "d/g.npz", False),
    ("**/*.pyc", "agent/__pycache__/x.pyc", True), ("docs", "docsx/a", False),
])
def test_dockerignore_matching(pattern, path, ignored):
    assert check_docker.is_ignored(path, [(pattern, False)]) is ignored
    assert check_docker.is_ignored(path, [(pattern, False), (pattern, True)]) is False


def test_compose_checks_fail_on_a_hard_coded_step_count_and_a_missing_service(tmp_path):
    text = (ROOT / "docker" / "compose.yaml").read_text()
    bad = text.replace('"${SOCMON_STEPS:-1000}"', '"1000"').replace("  standby4:", "  spare4:")
    (tmp_path / "compose.yaml").write_text(bad)
    problems = []
    check_docker.check_compose(problems, ENV, tmp_path / "compose.yaml")
    assert "compose.yaml: world: --steps does not come from SOCMON_STEPS" in problems
    assert "compose.yaml: services missing: standby4" in problems


def test_compose_check_runs_each_command_through_socmons_parser(tmp_path):
    text = (ROOT / "docker" / "compose.yaml").read_text()
    (tmp_path / "compose.yaml").write_text(text.replace('"--events"', '"--event-log"'))
    problems = []
    check_docker.check_compose(problems, ENV, tmp_path / "compose.yaml")
    assert len(problems) == 1 and problems[0].startswith("compose.yaml: monitor: socmon rejects")


def test_dockerfile_check_fails_without_the_base_argument(tmp_path):
    text = (ROOT / "docker" / "Dockerfile").read_text()
    (tmp_path / "Dockerfile").write_text(text.replace("FROM ${BASE}", "FROM python:3.11-slim"))
    problems = []
    check_docker.check_dockerfile(problems, tmp_path / "Dockerfile")
    assert problems == ["Dockerfile: the first FROM does not use BASE: FROM python:3.11-slim"]


def test_ignore_check_fails_when_venv_or_a_package_is_mishandled():
    rules = [(p, n) for p, n in check_docker.read_ignore() if not p.endswith(".venv")]
    problems = []
    check_docker.check_ignore(rules + [("agent", False)], ["agent"], problems)
    assert problems == [".dockerignore: .venv/bin/python would be in the build context",
                        ".dockerignore: excludes 'agent', which the Dockerfile copies"]


def test_compose_checks_the_monitor_wait_and_the_watch_stopped_first(tmp_path):
    text = (ROOT / "docker" / "compose.yaml").read_text()
    bad = text.replace(' "--wait-monitor", "1",', "").replace(
        "      monitor: { condition: service_started }\n", "")
    assert bad.count("service_started") == text.count("service_started") - 1
    (tmp_path / "compose.yaml").write_text(bad)
    problems = []
    check_docker.check_compose(problems, ENV, tmp_path / "compose.yaml")
    assert problems == [
        "compose.yaml: world: the clock does not wait for the monitor (--wait-monitor)",
        "compose.yaml: watch: does not depend on monitor (stopped after them)"]


def test_dockerfile_check_fails_when_pip_installs_into_the_system_python(tmp_path):
    text = (ROOT / "docker" / "Dockerfile").read_text()
    assert 'RUN python3 -m venv "$VIRTUAL_ENV"\n' in text
    (tmp_path / "Dockerfile").write_text(text.replace('RUN python3 -m venv "$VIRTUAL_ENV"\n', ""))
    problems = []
    check_docker.check_dockerfile(problems, tmp_path / "Dockerfile")
    assert problems == ["Dockerfile: pip installs before a venv is made (python3 -m venv)"]


def test_docker_times_parse_with_nanoseconds():
    assert check_docker._docker_time("1970-01-01T00:00:01.123456789Z") == pytest.approx(
        1.123456789)
    assert check_docker._docker_time("1970-01-01T01:00:02+01:00") == 2.0

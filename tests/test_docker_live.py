"""docker/ for real: the image built on a base, docker/compose.yaml brought up (world, three
agents, a standby, the monitor, gains and watch in containers of their own on one docker
network), agent 2's container killed with ``docker kill``, the monitor's verdict and the
standby's takeover waited for, the run stopped with SIGTERM (``compose stop``), and
everything the run made removed (``compose down -v``) whatever happened.

Marked ``docker`` (deselected by default; ``pytest -m docker``): it needs a Docker engine,
compose (``docker compose`` or ``docker-compose``) and a base image, ``socmon-base:bookworm``
or ``python:3.11-slim``, or mmdebstrap to make the first (docker/make-base.sh, about a
minute); ``SOCMON_DOCKER_BASE`` names another. It skips with the reason where one is
missing. The steps live in scripts/check_docker.py (``live_run``; ``--live`` runs them from
the command line).
"""

import importlib.util
import os
import secrets
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
spec = importlib.util.spec_from_file_location("check_docker", ROOT / "scripts" / "check_docker.py")
check_docker = sys.modules.get("check_docker") or importlib.util.module_from_spec(spec)
if "check_docker" not in sys.modules:
    sys.modules["check_docker"] = check_docker
    spec.loader.exec_module(check_docker)

pytestmark = [pytest.mark.docker, pytest.mark.slow]


def _left_behind(project):
    label = f"label=com.docker.compose.project={project}"
    left = {}
    for kind in ("container", "network", "volume"):
        out = subprocess.run(["docker", kind, "ls", "-q", "--filter", label]
                             + (["-a"] if kind == "container" else []),
                             capture_output=True, text=True).stdout.split()
        if out:
            left[kind] = out
    return left


def test_compose_run_survives_docker_kill_of_an_agent():
    why = check_docker.live_unavailable_reason()
    if why:
        pytest.skip(why)
    try:
        base = check_docker.find_base(os.environ.get("SOCMON_DOCKER_BASE"))
    except check_docker.Unavailable as exc:
        pytest.skip(str(exc))
    project = f"socmontest{secrets.token_hex(4)}"          # a project of this run only
    try:
        fig = check_docker.live_run(base, project=project, steps=6000)
    finally:
        assert _left_behind(project) == {}
    print(fig)
    # the monitor convicted agent 2 of a crash (its liveliness token went with its
    # container's connections) within a few seconds, and agent 4, the standby, took its role
    assert (fig["killed"], fig["cause"]) == (2, "crash")
    assert 0 <= fig["detection_s"] < 5.0
    assert [(r["failed"], r["by"]) for r in fig["replacements"]] == [(2, 4)]
    assert fig["last_step"] < fig["takeover_step"]
    assert sorted(fig["roster_after"]) == [1, 3, 4]
    # compose stop: every process ended on SIGTERM (watch with 130, its "interrupted"),
    # the killed one by SIGKILL
    codes = fig["exit_codes"]
    assert codes.pop("agent2") == 137 and codes.pop("watch") in (0, 130)
    assert set(codes.values()) == {0}, codes
    # the watch wrote its run folder on the volume, the failure and the recovery in it; it
    # was stopped first (it depends on every process it records): the monitor did not
    # leave the run before the watch did
    summary = fig["watched_summary"]
    assert summary is not None and summary["ended"] == "interrupted"
    assert [(f["agent"], f["cause"], f["replacement"]["agent"], f["activate_at"])
            for f in summary["failures"]] == [(2, "crash", 4, fig["takeover_step"])]
    assert summary["recovered"] is True and summary["no_monitor"] == [], summary["warnings"]

"""Check docker/ without a Docker engine (and build the image when there is one).

Without an engine (no daemon, no registry) it checks:

1. ``docker/compose.yaml`` parses as YAML, has the services gains, world, agent1..3,
   standby4, monitor and watch, every socmon service builds from ``docker/Dockerfile`` with the
   build argument BASE, mounts the ``runs`` volume on /runs, the world's step count
   comes from ``SOCMON_STEPS`` and its clock waits for the monitor, and the watch depends on
   every process it records (so that compose stops it first); each service's command, after
   compose's ``${VAR:-default}`` substitution, is accepted by socmon's own argument parser.
2. ``docker/Dockerfile`` declares ``ARG BASE`` before the first ``FROM``, which uses it,
   makes a venv before the first ``pip install`` (Debian's python is externally managed),
   and every ``COPY`` source exists in the build context.
3. ``.dockerignore`` excludes .venv, .git and run folders, and keeps everything the
   Dockerfile copies; the context it leaves is measured (files and bytes).
4. The image's install step from that same context: the files the Dockerfile copies,
   filtered by ``.dockerignore``, are copied to a temporary folder and ``pip wheel
   --no-deps`` builds socmon from there with this machine's Python (standing in for the
   base image's). With ``--venv`` the wheel is also installed, with its dependencies, into
   a fresh virtual environment and ``socmon --help`` runs.

With ``--build BASE[,BASE...]`` and a reachable engine, ``docker build`` runs for each base.

With ``--live`` and an engine with compose (``docker compose`` or ``docker-compose``), the
run itself (``live_run``; ``tests/test_docker_live.py`` runs the same): the image is built
on the base (``--base``; by default ``socmon-base:bookworm`` or ``python:3.11-slim`` when one
is present, else ``docker/make-base.sh --host-ca`` makes the first when mmdebstrap is
installed), ``docker/compose.yaml`` is brought up under a project name of its own, agent 2's
container is killed (``docker kill``) once the clock has run, and the monitor's verdict,
its reassignment to the standby, the standby's confirmation and the steps after it are
waited for, each with a deadline; ``compose stop`` (SIGTERM) then ends the run, the exit
statuses and the watch's run folder are read, and ``compose down -v`` removes the
containers, the network and the volume whatever happened. It prints the build time, the
image size, the time from the kill command to the verdict and the step the standby took
over from.

Exit status 0 when every check passed, 1 otherwise; each failure is one line.

``.dockerignore`` matching follows Docker's rules for the patterns used here (``*``,
``**``, a pattern also excluding what is under a matching folder, ``!`` exceptions); it is
not a full reimplementation of Docker's matcher.

Usage::

    python scripts/check_docker.py [--venv] [--build python:3.11-slim,python:3.12-slim]
    python scripts/check_docker.py --skip-install --live [--base socmon-base:bookworm]
"""

from __future__ import annotations

import argparse
import fnmatch
import json
import os
import re
import secrets
import shlex
import shutil
import subprocess
import sys
import tempfile
import time
from datetime import datetime
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

COMPOSE = ROOT / "docker" / "compose.yaml"
DOCKERFILE = ROOT / "docker" / "Dockerfile"
DOCKERIGNORE = ROOT / ".dockerignore"
SERVICES = ("gains", "world", "agent1", "agent2", "agent3", "standby4", "monitor", "watch")
#: paths (relative to the context) that must never reach the image's context
MUST_EXCLUDE = (".venv/bin/python", ".git/HEAD", "runs/x/summary.json",
                "design/runs/summary.json", "agent/__pycache__/cli.cpython-311.pyc",
                "gains.npz")
_VAR = re.compile(r"\$\$|\$\{([A-Za-z_][A-Za-z0-9_]*)(?::?-([^}]*))?\}")
_SHELL_VAR = re.compile(r"\$\{?([A-Za-z_][A-Za-z0-9_]*)\}?")


# ------------------------------------------------------------------------ .dockerignore

def read_ignore(path: Path = DOCKERIGNORE) -> list:
    """(pattern, negated) pairs of a .dockerignore, comments and blanks left out."""
    rules = []
    for line in path.read_text().splitlines():
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        neg = line.startswith("!")
        pattern = os.path.normpath(line[1:] if neg else line).lstrip("/")
        rules.append((pattern, neg))
    return rules


def _match(pattern: str, rel: str) -> bool:
    """Docker's rule: a pattern matches a path or any folder above it."""
    parts = rel.split("/")
    prefixes = ["/".join(parts[:i]) for i in range(1, len(parts) + 1)]
    regex = re.escape(pattern).replace(r"\*\*/", "(?:.*/)?").replace(r"\*\*", ".*")
    regex = regex.replace(r"\*", "[^/]*").replace(r"\?", "[^/]")
    return any(re.fullmatch(regex, p) for p in prefixes)


def is_ignored(rel: str, rules: list) -> bool:
    ignored = False
    for pattern, neg in rules:              # the last matching rule wins
        if _match(pattern, rel):
            ignored = not neg
    return ignored


def context_files(root: Path, rules: list):
    """Files of the build context that .dockerignore lets through (relative paths)."""
    for dirpath, dirnames, filenames in os.walk(root):
        rel_dir = os.path.relpath(dirpath, root)
        rel_dir = "" if rel_dir == "." else rel_dir + "/"
        # a folder excluded with no exception below it is not walked (.venv, .git)
        dirnames[:] = [d for d in dirnames if not (is_ignored(rel_dir + d, rules)
                                                   and not any(n for _, n in rules))]
        for name in filenames:
            rel = rel_dir + name
            if not is_ignored(rel, rules):
                yield rel


def check_ignore(rules: list, sources: list, problems: list) -> None:
    """Checks 3: what must stay out of the context does, what the image needs stays in."""
    for rel in MUST_EXCLUDE:
        if not is_ignored(rel, rules):
            problems.append(f".dockerignore: {rel} would be in the build context")
    for src in sources:
        if is_ignored(src, rules) or is_ignored(f"{src}/__init__.py", rules):
            problems.append(f".dockerignore: excludes {src!r}, which the Dockerfile copies")


# ------------------------------------------------------------------------ Dockerfile

def dockerfile_instructions(path: Path = DOCKERFILE) -> list:
    """(INSTRUCTION, arguments) of a Dockerfile, continuation lines joined."""
    text = re.sub(r"\\\n", " ", path.read_text())
    out = []
    for line in text.splitlines():
        line = line.strip()
        if line and not line.startswith("#"):
            word, _, rest = line.partition(" ")
            out.append((word.upper(), rest.strip()))
    return out


def check_dockerfile(problems: list, path: Path = DOCKERFILE) -> list:
    """Checks 2; returns the COPY sources."""
    ins = dockerfile_instructions(path)
    first_from = next((i for i, (w, _) in enumerate(ins) if w == "FROM"), None)
    args_before = [a.split("=")[0] for w, a in ins[:first_from or 0] if w == "ARG"]
    if first_from is None:
        problems.append("Dockerfile: no FROM")
        return []
    if "BASE" not in args_before:
        problems.append("Dockerfile: no ARG BASE before the first FROM")
    if not re.fullmatch(r"\$\{?BASE\}?(\s+AS\s+\S+)?", ins[first_from][1], re.IGNORECASE):
        problems.append(f"Dockerfile: the first FROM does not use BASE: "
                        f"FROM {ins[first_from][1]}")
    # Debian's python is externally managed (PEP 668): pip installs into a venv made first
    runs = [a for w, a in ins if w == "RUN"]
    first_pip = next((i for i, a in enumerate(runs) if re.search(r"\bpip\b.*\binstall\b", a)),
                     None)
    if first_pip is not None and not any(re.search(r"-m venv\b", a) for a in runs[:first_pip]):
        problems.append("Dockerfile: pip installs before a venv is made (python3 -m venv)")
    sources = []
    for word, rest in ins:
        if word == "COPY":
            parts = [p for p in shlex.split(rest) if not p.startswith("--")]
            sources += parts[:-1]
    for src in sources:
        if not (ROOT / src).exists():
            problems.append(f"Dockerfile: COPY source {src!r} is not in the context")
    return sources


# ------------------------------------------------------------------------ compose

def substitute(value: str, env: dict) -> str:
    """compose's ``${VAR}``, ``${VAR:-default}``; ``$$`` is a literal ``$``.

    >>> substitute("a ${X:-1} ${Y:-2} $${Z}", {"X": "7"})
    'a 7 2 ${Z}'
    """
    return _VAR.sub(lambda m: "$" if m.group(0) == "$$"
                    else env.get(m.group(1)) or (m.group(2) or ""), value)


def check_compose(problems: list, env: dict, path: Path = COMPOSE) -> dict:
    import yaml

    from agent.cli.main import build_parser

    try:
        doc = yaml.safe_load(path.read_text())
    except yaml.YAMLError as exc:
        problems.append(f"compose.yaml: not YAML: {' '.join(str(exc).split())}")
        return {}
    services = doc.get("services") or {}
    missing = [s for s in SERVICES if s not in services]
    if missing:
        problems.append(f"compose.yaml: services missing: {', '.join(missing)}")
    if "runs" not in (doc.get("volumes") or {}):
        problems.append("compose.yaml: no top-level volume 'runs'")
    parser = build_parser()
    for name, svc in services.items():
        build = svc.get("build") or {}
        if build.get("dockerfile") != "docker/Dockerfile" or "BASE" not in (build.get("args")
                                                                          or {}):
            problems.append(f"compose.yaml: {name}: not built from docker/Dockerfile with "
                            f"the build argument BASE")
        if "runs:/runs" not in (svc.get("volumes") or []):
            problems.append(f"compose.yaml: {name}: the runs volume is not mounted on /runs")
        command = [substitute(str(c), env) for c in svc.get("command") or []]
        if svc.get("entrypoint") == ["sh", "-c"]:
            senv = {**env, **{k: substitute(str(v), env)
                              for k, v in (svc.get("environment") or {}).items()}}
            script = command[0] if command else ""      # then the shell expands $VAR
            script = _SHELL_VAR.sub(lambda m: senv.get(m.group(1), m.group(0)), script)
            argvs = [shlex.split(part.strip())[1:] for part in script.split("&&")
                     if part.strip().startswith("socmon ")]
            if not argvs:
                problems.append(f"compose.yaml: {name}: its shell command runs no socmon")
        else:
            argvs = [command]
        for argv in argvs:
            try:
                parser.parse_args(argv)
            except SystemExit:
                problems.append(f"compose.yaml: {name}: socmon rejects its command "
                                f"{' '.join(argv)!r}")
    world = [substitute(str(c), env) for c in (services.get("world") or {}).get("command", [])]
    if "--steps" not in world or world[world.index("--steps") + 1] != env.get(
            "SOCMON_STEPS", "1000"):
        problems.append("compose.yaml: world: --steps does not come from SOCMON_STEPS")
    if "--wait-monitor" not in world:
        problems.append("compose.yaml: world: the clock does not wait for the monitor "
                        "(--wait-monitor)")
    # compose stops a service before those it depends on: the watch goes first, so that the
    # run folder it writes does not see the monitor and the agents leave before it
    needs = set((services.get("watch") or {}).get("depends_on") or {})
    recorded = {s for s in SERVICES if s not in ("gains", "watch")}
    if services.get("watch") is not None and not recorded <= needs:
        problems.append(f"compose.yaml: watch: does not depend on "
                        f"{', '.join(sorted(recorded - needs))} (stopped after them)")
    return services


# ------------------------------------------------------------------------ install

def check_install(sources: list, rules: list, problems: list, venv: bool) -> None:
    with tempfile.TemporaryDirectory(prefix="check_docker_") as tmp:
        ctx = Path(tmp) / "context"
        for rel in context_files(ROOT, rules):
            if any(rel == s or rel.startswith(s.rstrip("/") + "/") for s in sources):
                (ctx / rel).parent.mkdir(parents=True, exist_ok=True)
                shutil.copy2(ROOT / rel, ctx / rel)
        proc = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "-q",
                               "-w", str(Path(tmp) / "wheels"), str(ctx)],
                              capture_output=True, text=True)
        if proc.returncode != 0:
            problems.append(f"install: pip wheel from the filtered context failed: "
                            f"{' '.join(proc.stderr.split())[-300:]}")
            return
        wheel = next((Path(tmp) / "wheels").glob("socmon-*.whl"))
        print(f"install: built {wheel.name} from the filtered context")
        if venv:
            env_dir = Path(tmp) / "venv"
            subprocess.run([sys.executable, "-m", "venv", str(env_dir)], check=True)
            proc = subprocess.run([str(env_dir / "bin" / "pip"), "install", "-q", str(wheel)],
                                  capture_output=True, text=True)
            ok = proc.returncode == 0 and subprocess.run(
                [str(env_dir / "bin" / "socmon"), "--help"], capture_output=True).returncode == 0
            if not ok:
                problems.append(f"install: pip install of the wheel in a fresh venv failed: "
                                f"{' '.join(proc.stderr.split())[-300:]}")
            else:
                print("install: the wheel installs with its dependencies in a fresh venv and "
                      "socmon --help runs")


def engine_available() -> bool:
    try:
        return subprocess.run(["docker", "info"], capture_output=True,
                              timeout=20).returncode == 0
    except (OSError, subprocess.TimeoutExpired):
        return False


# ------------------------------------------------------------------------ live run

MAKE_BASE = ROOT / "docker" / "make-base.sh"
#: the base docker/make-base.sh makes, and the Dockerfile's default
DEBIAN_BASE, REGISTRY_BASE = "socmon-base:bookworm", "python:3.11-slim"
IMAGE = "socmon"


class Unavailable(Exception):
    """What this machine lacks for a live run (an engine, compose, a base image)."""


def _run(cmd, timeout=60.0, **kw):
    return subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, **kw)


def compose_command() -> list | None:
    """``docker compose`` (v2) where the plugin is installed, else ``docker-compose`` (v1)."""
    for cmd in (["docker", "compose"], ["docker-compose"]):
        try:
            if _run(cmd + ["version"], timeout=30).returncode == 0:
                return cmd
        except (OSError, subprocess.TimeoutExpired):
            pass
    return None


def image_present(name: str) -> bool:
    return _run(["docker", "image", "inspect", name]).returncode == 0


def live_unavailable_reason() -> str | None:
    """Why a live run cannot start here (None when it can, a base image aside)."""
    if shutil.which("docker") is None:
        return "no docker command on this machine"
    if not engine_available():
        return "no Docker engine answers (docker info failed)"
    if compose_command() is None:
        return "neither 'docker compose' nor 'docker-compose' is installed"
    return None


def find_base(base: str | None = None, make: bool = True, log=print) -> str:
    """The base image of the build: ``base`` (pulled when absent), else the Debian base or
    python:3.11-slim when present, else the Debian base made with docker/make-base.sh
    (mmdebstrap). Raises Unavailable with the reason when there is none."""
    if base:
        if image_present(base):
            return base
        if _run(["docker", "pull", base], timeout=600).returncode == 0:
            return base
        raise Unavailable(f"base image {base} is neither present nor pullable")
    for name in (DEBIAN_BASE, REGISTRY_BASE):
        if image_present(name):
            return name
    if not make or shutil.which("mmdebstrap") is None:
        raise Unavailable(f"no base image ({DEBIAN_BASE} or {REGISTRY_BASE}) and no "
                          f"mmdebstrap to make {DEBIAN_BASE} with docker/make-base.sh")
    log(f"base: making {DEBIAN_BASE} with docker/make-base.sh --host-ca (mmdebstrap)")
    proc = _run(["sh", str(MAKE_BASE), "--host-ca"], timeout=1200)
    if proc.returncode != 0 or not image_present(DEBIAN_BASE):
        raise Unavailable(f"docker/make-base.sh failed: "
                          f"{' '.join((proc.stderr or proc.stdout).split())[-300:]}")
    log(f"base: {proc.stdout.strip().splitlines()[-1]}")
    return DEBIAN_BASE


def _docker_time(stamp: str) -> float:
    """Epoch seconds of docker's RFC 3339 time with nanoseconds (State.FinishedAt)."""
    m = re.fullmatch(r"(\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d)(?:\.(\d+))?(Z|[+-]\d\d:\d\d)", stamp)
    if not m:
        raise ValueError(f"not a docker time: {stamp!r}")
    whole = datetime.fromisoformat(m.group(1) + ("+00:00" if m.group(3) == "Z" else m.group(3)))
    return whole.timestamp() + float("0." + (m.group(2) or "0"))


def wait_for(what: str, check, deadline_s: float, every: float = 0.25):
    """Call ``check()`` every ``every`` s until it returns something true, and return
    that; TimeoutError naming ``what`` once ``deadline_s`` has passed."""
    end = time.monotonic() + deadline_s
    while True:
        got = check()
        if got:
            return got
        if time.monotonic() > end:
            raise TimeoutError(f"no {what} within {deadline_s:.0f} s")
        time.sleep(every)


_WATCH_LINE = re.compile(r"\bstep (-?\d+) .*\broster ([\d,]+) \(epoch (\d+)\)")


def live_run(base: str, *, project: str | None = None, run: str = "live", steps: int = 6000,
             victim: str = "agent2", log=print) -> dict:
    """Build the image on ``base``, bring docker/compose.yaml up under ``project``, kill
    the container of ``victim`` once the clock has run 100 steps, wait for the verdict, the
    standby's takeover and 100 steps after it, stop the run with SIGTERM and read what it
    left; always ``compose down -v`` at the end. Returns the figures and findings (raises
    TimeoutError, naming the condition, when one is not met in time)."""
    compose = compose_command()
    if compose is None:
        raise Unavailable("neither 'docker compose' nor 'docker-compose' is installed")
    project = project or f"socmonlive{secrets.token_hex(4)}"
    env = {**os.environ, "BASE": base, "SOCMON_RUN": run, "SOCMON_STEPS": str(steps),
           "SOCMON_SEED": "1", "SOCMON_SCENARIO": "paper-14-live"}
    dc = compose + ["-p", project, "-f", str(COMPOSE)]
    out: dict = {"project": project, "base": base, "compose": " ".join(compose)}
    ids: dict = {}

    def sh(cmd, timeout=120.0, check=True):
        proc = _run(cmd, timeout=timeout, env=env)
        if check and proc.returncode != 0:
            raise RuntimeError(f"{' '.join(cmd[:4])} ... failed: "
                               f"{' '.join((proc.stderr or proc.stdout).split())[-400:]}")
        return proc

    def logs(service):
        proc = sh(["docker", "logs", ids[service]], check=False)
        return proc.stdout + proc.stderr

    def events():
        proc = sh(["docker", "exec", ids["monitor"], "cat", f"/runs/{run}/events.jsonl"],
                  check=False)
        return [json.loads(line) for line in proc.stdout.splitlines() if line.strip()]

    def watched():
        """(step, roster, epoch) of the watch's newest line."""
        lines = _WATCH_LINE.findall(logs("watch"))
        return (int(lines[-1][0]), lines[-1][1], int(lines[-1][2])) if lines else (-1, "", 0)

    try:
        t0 = time.monotonic()
        sh(["docker", "build", "-q", "-f", str(DOCKERFILE), "--build-arg", f"BASE={base}",
            "-t", IMAGE, str(ROOT)], timeout=1800)
        out["build_s"] = round(time.monotonic() - t0, 1)
        out["image_bytes"] = int(sh(["docker", "image", "inspect", "--format", "{{.Size}}",
                                     IMAGE]).stdout)
        log(f"build: {IMAGE} on {base} in {out['build_s']} s, "
            f"{out['image_bytes'] / 1e6:.0f} MB")
        t0 = time.monotonic()
        sh(dc + ["up", "-d", "--no-build"], timeout=300)
        for svc in SERVICES:
            ids[svc] = sh(dc + ["ps", "-q", svc]).stdout.strip()
        wait_for("clock start (world)", lambda: "clock starts" in logs("world"), 180)
        out["up_to_clock_s"] = round(time.monotonic() - t0, 1)
        wait_for("step 100 (watch)", lambda: watched()[0] >= 100, 60)
        log(f"up: {project}: the clock started {out['up_to_clock_s']} s after compose up")

        t_kill = time.time()
        sh(["docker", "kill", ids[victim]])
        killed = int(victim.removeprefix("agent"))
        finished = _docker_time(sh(["docker", "inspect", "--format", "{{.State.FinishedAt}}",
                                    ids[victim]]).stdout.strip())

        def answered():
            ev = events()
            verdict = next((e for e in ev if e.get("kind") == "verdict"
                            and e.get("agent") == killed), None)
            reassign = next((e for e in ev if e.get("kind") == "reassign"
                             and killed in e.get("failed", [])), None)
            confirmed = reassign and next((e for e in ev if e.get("kind") == "confirmed"
                                           and e.get("epoch") == reassign["epoch"]), None)
            return confirmed and (verdict, reassign, confirmed)

        verdict, reassign, confirmed = wait_for("verdict, reassignment and confirmation "
                                                "(monitor events.jsonl)", answered, 30)
        out.update(killed=killed, cause=verdict["cause"], evidence=verdict.get("evidence"),
                   last_step=verdict["step"], takeover_step=reassign["activate_at"],
                   replacements=reassign["replacements"], epoch=reassign["epoch"],
                   # from the kill command (the daemon stamps the container's end,
                   # FinishedAt, once it has reaped it: about when the monitor hears it)
                   detection_s=round(verdict["detected_t"] - t_kill, 3),
                   verdict_s=round(verdict["t"] - t_kill, 3),
                   confirmed_s=round(confirmed["t"] - t_kill, 3),
                   finished_s=round(finished - t_kill, 3))
        log(f"kill: docker kill {victim}; verdict {verdict['cause']} "
            f"({verdict.get('evidence')}) {out['detection_s']} s later, at step "
            f"{verdict['step']}; "
            f"{reassign['replacements']} from step {reassign['activate_at']}, confirmed "
            f"{out['confirmed_s']} s after the kill")
        after = reassign["activate_at"] + 100
        step, roster, epoch = wait_for(
            f"step {after} under epoch {reassign['epoch']} (watch)",
            lambda: (lambda w: w if w[0] >= after and w[2] == reassign["epoch"] else None)(
                watched()), 60)
        out["roster_after"] = [int(i) for i in roster.split(",")]

        t0 = time.monotonic()
        sh(dc + ["stop", "-t", "20"], timeout=120)
        out["stop_s"] = round(time.monotonic() - t0, 1)
        out["exit_codes"] = {svc: int(sh(["docker", "inspect", "--format",
                                          "{{.State.ExitCode}}", ids[svc]]).stdout)
                             for svc in SERVICES}
        proc = sh(["docker", "run", "--rm", "-v", f"{project}_runs:/runs", "--entrypoint",
                   "cat", IMAGE, f"/runs/{run}/watched/summary.json"], check=False)
        out["watched_summary"] = json.loads(proc.stdout) if proc.returncode == 0 else None
        log(f"stop: {out['stop_s']} s (SIGTERM); exit statuses {out['exit_codes']}")
    except BaseException:
        for svc in ids:                                 # what the processes said, for the why
            log(f"--- {svc} (last lines)\n" + "\n".join(logs(svc).splitlines()[-8:]))
        raise
    finally:
        # whatever happened: the containers, the network and the volume of this project go
        _run(dc + ["down", "-v", "--remove-orphans", "-t", "10"], timeout=180, env=env)
        label = f"label=com.docker.compose.project={project}"
        for kind, rm in (("container", ["rm", "-f"]), ("network", ["network", "rm"]),
                         ("volume", ["volume", "rm", "-f"])):
            left = _run(["docker", kind, "ls", "-q", "--filter", label]
                        + (["-a"] if kind == "container" else [])).stdout.split()
            if left:
                _run(["docker", *rm, *left])
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--venv", action="store_true",
                        help="also install the wheel with its dependencies in a fresh venv")
    parser.add_argument("--build", metavar="BASES",
                        help="comma-separated base images to docker build from (needs an "
                             "engine)")
    parser.add_argument("--skip-install", action="store_true",
                        help="do not build the wheel (checks 1-3 only)")
    parser.add_argument("--live", action="store_true",
                        help="build the image, run docker/compose.yaml, kill agent 2's "
                             "container and wait for the standby to take over (needs an "
                             "engine and compose; removes what it started)")
    parser.add_argument("--base", metavar="IMAGE",
                        help=f"base image of --live (default: {DEBIAN_BASE} or "
                             f"{REGISTRY_BASE} when present, else {DEBIAN_BASE} made with "
                             f"docker/make-base.sh)")
    parser.add_argument("--steps", type=int, default=6000,
                        help="the world's steps in --live (default 6000, 2 minutes at most)")
    args = parser.parse_args(argv)
    problems: list = []
    env = {"SOCMON_STEPS": "1234", "SOCMON_RUN": "check", "SOCMON_SCENARIO": "paper-14-live",
           "SOCMON_SEED": "5", "BASE": "python:3.12-slim"}
    services = check_compose(problems, env)
    print(f"compose: {len(services)} services ({', '.join(services)}) checked")
    sources = check_dockerfile(problems)
    print(f"Dockerfile: ARG BASE / FROM ${{BASE}} checked; COPY {' '.join(sources)}")
    rules = read_ignore()
    check_ignore(rules, sources, problems)
    files = list(context_files(ROOT, rules))
    size = sum((ROOT / f).stat().st_size for f in files)
    print(f".dockerignore: build context {len(files)} files, {size / 1e6:.2f} MB")
    if not args.skip_install:
        check_install(sources, rules, problems, args.venv)
    if args.build:
        if not engine_available():
            problems.append("--build: no Docker engine answers (docker info failed)")
        for base in (args.build.split(",") if engine_available() else []):
            proc = subprocess.run(["docker", "build", "-f", str(DOCKERFILE), "--build-arg",
                                   f"BASE={base}", "-t", f"socmon-check:{base.replace(':', '-')}",
                                   str(ROOT)], capture_output=True, text=True)
            if proc.returncode != 0:
                problems.append(f"docker build from {base} failed: "
                                f"{' '.join(proc.stderr.split())[-300:]}")
            else:
                print(f"docker build from {base}: ok")
    elif not engine_available():
        print("engine: none answers here; docker build and compose up were not run")
    if args.live:
        why = live_unavailable_reason()
        try:
            if why:
                raise Unavailable(why)
            figures = live_run(find_base(args.base), steps=args.steps)
            print("live: " + json.dumps({k: v for k, v in figures.items()
                                         if k != "watched_summary"}))
        except (Unavailable, TimeoutError, RuntimeError, subprocess.TimeoutExpired) as exc:
            problems.append(f"--live: {exc}")
    for p in problems:
        print(f"FAIL {p}")
    print("all checks passed" if not problems else f"{len(problems)} check(s) failed")
    return 0 if not problems else 1


if __name__ == "__main__":
    sys.exit(main())

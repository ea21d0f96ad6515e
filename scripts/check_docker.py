"""Check docker/ without a Docker engine (and build the image when there is one).

Without an engine (no daemon, no registry) it checks:

1. ``docker/compose.yaml`` parses as YAML, has the services gains, world, agent1..3,
   standby4, monitor and watch, every socmon service builds from ``docker/Dockerfile`` with the
   build argument BASE, mounts the ``runs`` volume on /runs, and the world's step count
   comes from ``SOCMON_STEPS``; each service's command, after compose's ``${VAR:-default}``
   substitution, is accepted by socmon's own argument parser.
2. ``docker/Dockerfile`` declares ``ARG BASE`` before the first ``FROM``, which uses it,
   and every ``COPY`` source exists in the build context.
3. ``.dockerignore`` excludes .venv, .git and run folders, and keeps everything the
   Dockerfile copies; the context it leaves is measured (files and bytes).
4. The image's install step from that same context: the files the Dockerfile copies,
   filtered by ``.dockerignore``, are copied to a temporary folder and ``pip wheel
   --no-deps`` builds socmon from there with this machine's Python (standing in for the
   base image's). With ``--venv`` the wheel is also installed, with its dependencies, into
   a fresh virtual environment and ``socmon --help`` runs.

With ``--build BASE[,BASE...]`` and a reachable engine, ``docker build`` runs for each base.
Exit status 0 when every check passed, 1 otherwise; each failure is one line.

``.dockerignore`` matching follows Docker's rules for the patterns used here (``*``,
``**``, a pattern also excluding what is under a matching folder, ``!`` exceptions); it is
not a full reimplementation of Docker's matcher.

Usage::

    python scripts/check_docker.py [--venv] [--build python:3.11-slim,python:3.12-slim]
"""

from __future__ import annotations

import argparse
import fnmatch
import os
import re
import shlex
import shutil
import subprocess
import sys
import tempfile
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


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--venv", action="store_true",
                        help="also install the wheel with its dependencies in a fresh venv")
    parser.add_argument("--build", metavar="BASES",
                        help="comma-separated base images to docker build from (needs an "
                             "engine)")
    parser.add_argument("--skip-install", action="store_true",
                        help="do not build the wheel (checks 1-3 only)")
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
    for p in problems:
        print(f"FAIL {p}")
    print("all checks passed" if not problems else f"{len(problems)} check(s) failed")
    return 0 if not problems else 1


if __name__ == "__main__":
    sys.exit(main())

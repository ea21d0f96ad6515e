"""Child processes of a live run on one machine: start, watch, stop, account.

Every child is a separate ``python -m agent.cli ...`` process started with
``subprocess.Popen(start_new_session=True)``: its own process group, so that stopping it
(SIGTERM, then SIGKILL after a grace period) reaches anything it started, and a Ctrl-C in
the terminal reaches only the launcher, which then stops the children itself. Children are
reaped with ``os.wait4`` to record their CPU time.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

__all__ = ["Child", "Children", "ROOT"]

#: The project root (children run ``python -m agent.cli`` from here).
ROOT = Path(__file__).resolve().parents[2]


@dataclass
class Child:
    name: str
    proc: subprocess.Popen
    log_path: Path
    returncode: int | None = None
    cpu_s: float | None = None
    ended_at: float | None = None
    _log: object = field(default=None, repr=False)


class Children:
    """The children of one run; :meth:`stop_all` is safe to call any number of times."""

    def __init__(self, log_dir: Path):
        self.log_dir = Path(log_dir)
        self.log_dir.mkdir(parents=True, exist_ok=True)
        self.children: dict = {}
        self._unreported: list = []   # exited children not yet returned by reap()

    def start(self, name: str, argv: list, wrap=()) -> Child:
        """Start ``python -m agent.cli *argv`` as ``name``; ``wrap`` is an argv prefix that
        execs it in place (e.g. ``ip netns exec NS``, :meth:`agent.testbed.netns.Testbed.exec_prefix`).
        """
        log_path = self.log_dir / f"{name}.log"
        log = open(log_path, "wb")
        env = dict(os.environ)
        env["PYTHONPATH"] = str(ROOT) + (os.pathsep + env["PYTHONPATH"]
                                         if env.get("PYTHONPATH") else "")
        env.setdefault("PYTHONUNBUFFERED", "1")
        # every child multiplies small matrices once per step: BLAS worker threads only
        # contend for the cores with the other processes of the run
        for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
            env.setdefault(var, "1")
        proc = subprocess.Popen([*wrap, sys.executable, "-m", "agent.cli", *argv], cwd=str(ROOT),
                                env=env, stdin=subprocess.DEVNULL, stdout=log,
                                stderr=subprocess.STDOUT, start_new_session=True)
        child = Child(name, proc, log_path, _log=log)
        self.children[name] = child
        return child

    def reap(self) -> list:
        """Children that exited since the last call, each returned exactly once (also when
        :meth:`running` found it first)."""
        self._collect()
        done, self._unreported = self._unreported, []
        return done

    def _collect(self) -> None:
        for child in self.children.values():
            if child.returncode is not None:
                continue
            try:
                pid, status, usage = os.wait4(child.proc.pid, os.WNOHANG)
            except ChildProcessError:
                pid, status, usage = child.proc.pid, 0, None
            if pid == 0:
                continue
            child.returncode = os.waitstatus_to_exitcode(status) if usage is not None else -1
            child.proc.returncode = child.returncode
            child.cpu_s = (usage.ru_utime + usage.ru_stime) if usage is not None else None
            child.ended_at = time.monotonic()
            child._log.close()
            self._unreported.append(child)

    def running(self) -> list:
        """Children still running; one that exited is kept for the next :meth:`reap`."""
        self._collect()
        return [c for c in self.children.values() if c.returncode is None]

    def signal_all(self, sig) -> None:
        for child in self.running():
            try:
                os.killpg(child.proc.pid, sig)
            except (ProcessLookupError, PermissionError):
                pass

    def wait_all(self, timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        while self.running():
            if time.monotonic() > deadline:
                return False
            time.sleep(0.02)
        return True

    def stop_all(self, grace: float = 5.0) -> None:
        """SIGTERM every process group, SIGKILL what is left after ``grace`` seconds."""
        self.signal_all(signal.SIGTERM)
        if not self.wait_all(grace):
            self.signal_all(signal.SIGKILL)
            self.wait_all(10.0)
        # a child's own children (none normally) die with its process group
        for child in self.children.values():
            try:
                os.killpg(child.proc.pid, signal.SIGKILL)
            except (ProcessLookupError, PermissionError):
                pass

    def tail(self, name: str, lines: int = 5) -> str:
        try:
            text = self.children[name].log_path.read_text(errors="replace")
        except OSError:
            return ""
        return "\n".join(text.strip().splitlines()[-lines:])

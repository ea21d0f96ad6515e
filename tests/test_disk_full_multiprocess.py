"""A run whose folder's disk fills up mid-run: the processes keep running (their logs lose
lines, the monitor's events go on on the wire), the crash is recovered, and ``up`` says in
one line which file could not be written, prints its summary and exits 3; what it did
write is whole. The disk is a 400 kB tmpfs the test mounts (root only; skipped
otherwise) and removes."""

import json
import os
import signal
import subprocess
import sys
import time

import pytest

from tests.test_runtime_multiprocess import ROOT, UP_TIMEOUT

pytestmark = [pytest.mark.multiprocess, pytest.mark.slow]


@pytest.fixture
def tiny_disk(tmp_path):
    mount = tmp_path / "disk"
    mount.mkdir()
    made = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=400k", "tmpfs", str(mount)],
                          capture_output=True, text=True)
    if made.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {made.stderr.strip() or made.returncode}")
    try:
        yield mount
    finally:
        subprocess.run(["umount", "-l", str(mount)], capture_output=True)


def test_a_full_disk_mid_run_loses_no_run_and_ends_in_one_line(tiny_disk, live_gains):
    out = tiny_disk / "run"
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    proc = subprocess.Popen([sys.executable, "-m", "agent.cli", "up", "paper-14-live",
                             "--gains", str(live_gains), "--out", str(out), "--json",
                             "--steps", "600", "--step-ms", "20", "--kill", "350:1"],
                            cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, start_new_session=True)
    try:
        deadline = time.monotonic() + UP_TIMEOUT
        while not (out / "run.json").is_file():     # the processes are started
            assert proc.poll() is None and time.monotonic() < deadline
            time.sleep(0.05)
        with open(tiny_disk / "filler", "wb", buffering=0) as f:  # to the last block
            try:
                while True:
                    f.write(b"\0" * 4096)
            except OSError:
                pass
        stdout, stderr = proc.communicate(timeout=UP_TIMEOUT)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.communicate()
    assert proc.returncode == 3, stderr
    assert "Traceback" not in stderr, stderr
    (line,) = [t for t in stderr.splitlines() if t.startswith("socmon up: run folder:")]
    assert "cannot write" in line and "No space left on device" in line, line
    summary = json.loads(stdout)
    assert [(f["agent"], f["cause"]) for f in summary["failures"]] == [(1, "crash")]
    assert summary["recovered"] is True
    assert not [p for p in out.iterdir() if p.name.endswith(".tmp")]
    for p in out.glob("*.json"):
        json.loads(p.read_text())                   # whatever was written is whole

"""A live deployment for multi-process tests: world + agents as OS processes on loopback.

Children are started by :class:`agent.run.launcher.Children` (own process groups) and always
stopped by the fixture, even when the test fails. The test process joins the mesh as a
``monitor`` peer and reads statuses and estimates. Every wait has a deadline.
"""

import os
import random
import subprocess
import sys
import time
from pathlib import Path

from agent.protocol import wire
from agent.run.launcher import ROOT, Children
from broker_free_net.ports import listen_port
from agent.protocol import topics
from broker_free_net.codec import MessageStats, try_decode
from broker_free_net.config import NetConfig

DEADLINE = 60.0  # generous: a loaded 2-core machine


class Deployment:
    def __init__(self, tmp: Path, scenario: str, gains: Path, n: int, agents=(1, 2, 3, 4),
                 step_ms=20, deadline_ms=None, seed=0, delays="none"):
        self.run = f"t{os.getpid()}x{random.randrange(10**9)}"
        self.children = Children(tmp / "logs")
        self.n = n
        port = [listen_port() for _ in range(len(agents) + 2)]
        self.ep = [f"tcp/127.0.0.1:{p}" for p in port]
        self.peer = topics.open_peer(NetConfig(run=self.run, listen=(self.ep[0],)), "monitor", 0)
        self.status_in = self.peer.subscribe(topics.any_agent_pattern(self.run, "status"))
        self.est_in = self.peer.subscribe(topics.any_agent_pattern(self.run, "est"), maxlen=1 << 16)
        self.status, self.est_epochs, self.stats = {}, {}, MessageStats()
        common = ["--run", self.run, "--connect", self.ep[0], "--seed", str(seed)]
        self.children.start("world", ["world", scenario, *common, "--listen", self.ep[1],
                                      "--step-ms", str(step_ms),
                                      "--wait-agents", ",".join(map(str, agents))])
        for c, a in enumerate(agents):
            argv = ["agent", scenario, "--id", str(a), *common, "--listen", self.ep[c + 2],
                    "--connect", self.ep[1], "--gains", str(gains), "--delays", delays]
            if deadline_ms is not None:
                argv += ["--deadline-ms", str(deadline_ms)]
            self.children.start(f"agent-{a}", argv)

    def read(self):
        for item in self.status_in.drain():
            m = try_decode(item.payload, wire.STATUS_SCHEMA, self.stats)
            if m is not None:
                self.status[m["agent"]] = m
        schema = wire.est_schema(self.n)
        for item in self.est_in.drain():
            m = try_decode(item.payload, schema, self.stats)
            if m is not None:
                self.est_epochs[(m["agent"], m["step"])] = m["epoch"]

    def wait_for(self, predicate, what, timeout=DEADLINE):
        deadline = time.monotonic() + timeout
        while True:
            self.read()
            dead = [c.name for c in self.children.reap() if c.returncode is not None]
            if dead:
                raise AssertionError(f"{dead} exited while waiting for {what}: "
                                     + "\n".join(self.children.tail(n) for n in dead))
            if predicate():
                return
            if time.monotonic() > deadline:
                raise AssertionError(f"timed out waiting for {what}; statuses: "
                                     f"{ {a: s['step'] for a, s in self.status.items()} }")
            self.peer.wait(timeout=0.1)

    def step_of(self, agent):
        return self.status.get(agent, {}).get("step", -1)

    def socmon(self, *argv, timeout=DEADLINE):
        """Run a socmon command against this deployment; returns CompletedProcess."""
        env = dict(os.environ, PYTHONPATH=str(ROOT))
        return subprocess.run([sys.executable, "-m", "agent.cli", *argv, "--run", self.run,
                               "--connect", self.ep[0]], cwd=ROOT, env=env, timeout=timeout,
                              capture_output=True, text=True, start_new_session=True)

    def close(self):
        try:
            self.children.stop_all(grace=5.0)
        finally:
            self.peer.close()

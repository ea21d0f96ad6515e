"""The kinds of fault a run injects (:class:`agent.run.local.Fault`), in one place for
``up``, ``chaos`` and the simulated runtime; pure (no transport), so that
:mod:`agent.run.simulated` reads them without loading zenoh."""

__all__ = ["FAULT_KINDS", "SCRIPTED_FAULTS", "WRONG_KINDS", "PROCESS_FAULTS", "MONITOR_FAULTS",
           "ROLE_FAULTS", "REPLAYED_FAULTS", "REPLAYED_WORDS"]

#: crash: the agent SIGKILLs itself after publishing step STEP-1 (reproducible);
#: kill: SIGKILL from outside at STEP; stop: SIGSTOP for ``seconds`` then SIGCONT;
#: monitor: SIGKILL the monitor and start it again; partition: every link out of the
#: agent cut for ``seconds``; delay: ``value`` steps of delay on every link into the
#: agent for ``seconds``; drop: drop probability ``value`` on every link into the agent
#: for ``seconds``.
#: hang: the agent's loop stops for good (SIGUSR1) while its token stays; sensor: the
#: agent's sensor readings stop (the world's link into it cut) for ``seconds``.
#: linkdown: the agent's host's link brought down for ``seconds`` (a real partition; a run
#: on a testbed of network namespaces only, :mod:`agent.testbed.netns`).
#: monitorsgone: every monitor (active and standby) SIGKILLed, none started again.
#: lie: the agent publishes its estimates VALUE noise std-devs off (scripted); bias, drift,
#: noise: its sensor goes wrong (scripted, :func:`design.simulate.apply_sensor_faults`).
FAULT_KINDS = ("crash", "kill", "stop", "hang", "sensor", "monitor", "partition", "delay",
               "drop", "linkdown", "worldstop", "monitorstop", "monitorsgone", "lie",
               "bias", "drift", "noise")
#: The kinds an agent process is told of at its start (scripted at a step, like a crash).
SCRIPTED_FAULTS = ("crash", "lie", "bias", "drift", "noise")
#: The kinds that leave an agent running but wrong: its estimates (``lie``) or its sensor
#: (``bias``) a few noise std-devs off from their step on (the residual tests' work).
WRONG_KINDS = ("lie", "bias")
#: The kinds that act on a process other than an agent (no AGENT in ``--fault``).
PROCESS_FAULTS = ("monitor", "worldstop", "monitorstop", "monitorsgone")
#: The kinds that act on the monitors (none runs with ``--no-monitor``).
MONITOR_FAULTS = ("monitor", "monitorstop", "monitorsgone")
#: The kinds that change only what an agent computes or publishes: a standby computes
#: and publishes nothing before it holds a role, so they act on it only once it holds one
#: (the live agent and the simulator alike).
ROLE_FAULTS = ("lie", "bias", "drift", "noise")
#: The kinds ``--check-simulator`` replays (:mod:`design.simulate`): a scripted crash at
#: its step, a lie and the sensor faults (its ``FAULT_KINDS``); the others act on timing,
#: processes or links, which the simulator does not model.
REPLAYED_FAULTS = ("crash", "lie", "bias", "drift", "noise")
#: ... said to the user.
REPLAYED_WORDS = "scripted crashes (--kill), lies and sensor faults (lie, bias, drift, noise)"

"""Whole runs: :mod:`~agent.run.local` a live run on this machine and its faults,
:mod:`~agent.run.launcher` its child processes, :mod:`~agent.run.simulated` the same
runtime in one process under simulated time, :mod:`~agent.run.recorder` what a peer hears
of a run, :mod:`~agent.run.folder` the run folder and its atomic writes,
:mod:`~agent.run.summary` what the record says, :mod:`~agent.run.chaos` random fault
schedules and the invariants a run must keep, :mod:`~agent.run.watch` attaching to a
run, :mod:`~agent.run.inject` changing a running deployment's links,
:mod:`~agent.run.terminal` what a live run prints, :mod:`~agent.run.web` its live page
(``--web``).

From flags to a process: :mod:`~agent.run.agent_options` (``socmon agent``),
:mod:`~agent.run.monitor_options` (``socmon monitor``), :mod:`~agent.run.chaos_report`
(``socmon chaos``'s report).

What the offline commands do beyond parsing their flags: :mod:`~agent.run.simulate`
(``socmon simulate``: a Monte-Carlo run of :mod:`design.simulate`, its figure and text)
and :mod:`~agent.run.reproduce` (``socmon reproduce``: the paper's Section 5 written to a
folder)."""

"""What every process shell shares: a log that a flood of messages cannot fill
(:mod:`~agent.shell.ratelimit`) and giving the C heap back after a burst
(:mod:`~agent.shell.memory`)."""

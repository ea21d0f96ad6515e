"""Scheduling priority: the monitor's loop and its urgent design process go first.

A failure detector that shares a loaded host with the work it watches must be scheduled
promptly, or its own stalls look like the agents' and its answers come late (corosync
runs its loop at real-time priority for this reason). The monitor's loop and the process
that designs an unforeseen failure's first gain use little CPU, in bursts, and their
latency is the network's time without a role; they ask for :data:`LATENCY_NICE`. The
precompute process keeps the niceness the monitor was started with (the agents'), the
refining one that plus ``BACKGROUND_NICE``: they are the CPU-heavy part and must not take
the agents' time.

Raising a priority needs root or ``CAP_SYS_NICE``; without them the monitor runs at the
niceness it was given and says so at start. Linux keeps a niceness per thread: it is set
on the thread that runs the loop, before the transport starts its threads (which inherit
it), and a spawned design process inherits it from that thread.

>>> now = niceness()
>>> raise_for_latency(target=now) == (now, now, f"at nice {now}")   # nothing to change
True
"""

from __future__ import annotations

import os

__all__ = ["LATENCY_NICE", "niceness", "set_niceness", "raise_for_latency"]

#: the niceness the monitor's loop and its urgent design process ask for (default 0;
#: -5 weighs a thread 3x a default one in Linux's fair scheduler)
LATENCY_NICE = -5


def niceness() -> int:
    """The calling thread's niceness (0 where the platform has none)."""
    try:
        return os.getpriority(os.PRIO_PROCESS, 0)
    except (OSError, AttributeError):
        return 0


def set_niceness(value: int) -> bool:
    """Set the calling thread's niceness to ``value``; False when not permitted."""
    try:
        os.setpriority(os.PRIO_PROCESS, 0, int(value))
    except (OSError, AttributeError):
        return False
    return True


def raise_for_latency(target: int = LATENCY_NICE) -> tuple:
    """``(niceness before, niceness now, words)``: the calling thread raised to ``target``
    when it runs below it and the system allows it; ``words`` say what came of it, for the
    log."""
    before = niceness()
    if before <= target:
        return before, before, f"at nice {before}"
    if set_niceness(target):
        return before, target, (f"at nice {target} (was {before}): its detector and first "
                                "gains go before the run's other work")
    return before, before, (f"at nice {before}: nice {target}, for its detector and first "
                            "gains, needs root or CAP_SYS_NICE")

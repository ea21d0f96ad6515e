"""Waits with deadlines for the multi-process tests: never a fixed sleep."""

import time


def wait_until(predicate, timeout: float, interval: float = 0.05) -> bool:
    """Poll ``predicate`` every ``interval`` s until it holds or ``timeout`` s passed;
    returns whether it holds (checked once more at the deadline).

    >>> wait_until(lambda: True, timeout=1.0)
    True
    >>> wait_until(lambda: False, timeout=0.0)
    False
    """
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(interval)
    return bool(predicate())

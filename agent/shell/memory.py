"""Process memory hygiene: giving the C heap back to the OS after a burst of input."""

from __future__ import annotations

import ctypes
import ctypes.util

__all__ = ["heap_trimmer", "TRIM_S"]

#: after a burst of messages, freed heap memory is returned to the OS at most this often
TRIM_S = 2.0


def heap_trimmer():
    """Return a function that gives freed heap pages back to the OS (glibc ``malloc_trim``).

    A burst of large or many messages leaves the C heap arenas of zenoh's threads at their
    high-water mark; trimming after such a burst keeps the agent's RSS flat. A no-op where
    glibc is not available.
    """
    try:
        trim = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6").malloc_trim
    except (OSError, AttributeError):
        return lambda: None
    trim.argtypes, trim.restype = [ctypes.c_size_t], ctypes.c_int
    return lambda: trim(0)

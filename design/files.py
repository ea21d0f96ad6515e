"""Files a user names, read at a bounded cost: a regular file of at most so many bytes.

Every file socmon reads on a user's word (a scenario, its edges CSV, a gains file) is
opened here. A FIFO, a device (``/dev/zero``), a directory or a socket is refused before a
byte is read (a FIFO is opened without waiting for a writer); so is a file larger than its
kind allows, by its size, and the read itself stops at the bound, so a file that grows
while it is read, or a ``/proc`` file that reports size 0, cannot make it longer.

Examples
--------
>>> import os, tempfile
>>> d = tempfile.mkdtemp()
>>> path = os.path.join(d, "s.toml")
>>> with open(path, "w") as f:
...     _ = f.write("name = 'x'")
>>> read_bounded(path, 100)
b"name = 'x'"
>>> read_bounded(path, 4)
Traceback (most recent call last):
...
design.files.UnreadableFile: 10 bytes, above the largest accepted here, 4 bytes
>>> read_bounded(d, 100)
Traceback (most recent call last):
...
design.files.UnreadableFile: is a directory, not a regular file
"""

from __future__ import annotations

import os
import stat

from .errors import SocmonError

__all__ = ["UnreadableFile", "open_bounded", "read_bounded", "file_kind", "human_bytes"]


class UnreadableFile(SocmonError):
    """A named file cannot be read within its bound; the message says why, without the
    path (the caller names the file and the field or flag that gave it)."""


def file_kind(mode: int) -> str:
    """What a non-regular file is, from its ``st_mode`` ("a FIFO (named pipe)", ...)."""
    for test, name in ((stat.S_ISDIR, "a directory"), (stat.S_ISFIFO, "a FIFO (named pipe)"),
                       (stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"),
                       (stat.S_ISSOCK, "a socket")):
        if test(mode):
            return name
    return "not a regular file"


def human_bytes(n: int) -> str:
    """``16 MiB`` for a whole number of MiB, else ``1234 bytes``.

    >>> human_bytes(16 << 20), human_bytes(1000)
    ('16 MiB', '1000 bytes')
    """
    if n >= 1 << 20 and n % (1 << 20) == 0:
        return f"{n >> 20} MiB"
    if n >= 1 << 10 and n % (1 << 10) == 0:
        return f"{n >> 10} KiB"
    return f"{n} bytes"


def open_bounded(path, max_bytes: int):
    """Open ``path`` for binary reading if it is a regular file of at most ``max_bytes``.

    Returns ``(file, size)``; the caller closes the file and reads at most ``size`` bytes
    of it (``size`` is the size at open time, at most ``max_bytes``).

    Raises
    ------
    UnreadableFile
        No such file, permission denied, not a regular file, or larger than ``max_bytes``.
    """
    flags = os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0)
    try:
        fd = os.open(os.fspath(path), flags)
    except FileNotFoundError:
        raise UnreadableFile("no such file") from None
    except OSError as exc:
        raise UnreadableFile(exc.strerror or str(exc)) from None
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            kind = file_kind(st.st_mode)
            raise UnreadableFile(f"is {kind}, not a regular file" if kind.startswith("a ")
                                 else kind)
        _check_size(st.st_size, max_bytes)
        f = os.fdopen(fd, "rb")
    except BaseException:
        os.close(fd)
        raise
    return f, st.st_size


def read_bounded(path, max_bytes: int) -> bytes:
    """The bytes of the regular file ``path``, refused beyond ``max_bytes`` (see the module)."""
    f, _ = open_bounded(path, max_bytes)
    with f:
        try:
            data = f.read(max_bytes + 1)
        except OSError as exc:
            raise UnreadableFile(exc.strerror or str(exc)) from None
    if len(data) > max_bytes:   # grew since it was opened
        raise UnreadableFile(f"more than {human_bytes(max_bytes)}, the largest accepted here")
    return data


def _check_size(size: int, max_bytes: int) -> None:
    if size > max_bytes:
        raise UnreadableFile(f"{size} bytes, above the largest accepted here, "
                             f"{human_bytes(max_bytes)}")

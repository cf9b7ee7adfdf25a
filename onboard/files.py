"""Reading a file named on the command line: a regular file only, its size checked before a
byte is read.

``open()`` on a FIFO waits for a writer (for ever); ``read()`` on /dev/zero never ends; a
directory raises IsADirectoryError only when read. So the file is opened without blocking
(``O_NONBLOCK``: a FIFO opens at once, with or without a writer), checked with ``fstat`` on the
descriptor that will be read (no window between the check and the read), and refused unless it
is a regular file no larger than the caller's limit. Errors are ``FileRefused`` (a ValueError)
with one line naming the file and the reason.
"""
from __future__ import annotations

import os
import stat
from pathlib import Path
from typing import IO


class FileRefused(ValueError):
    """The file cannot be used; the message names it and says why."""


def open_regular(path: str | os.PathLike, max_bytes: int | None = None, text: bool = False) -> IO:
    """``path`` opened for reading if it is a regular file of at most ``max_bytes``."""
    name = os.fspath(path)
    try:
        fd = os.open(name, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_NOCTTY", 0))
    except OSError as exc:
        raise FileRefused(f"{name}: cannot read: {exc.strerror or exc}") from None
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            kind = ("a directory" if stat.S_ISDIR(st.st_mode) else "a FIFO" if stat.S_ISFIFO(st.st_mode)
                    else "a device" if stat.S_ISCHR(st.st_mode) or stat.S_ISBLK(st.st_mode) else "not a file")
            raise FileRefused(f"{name}: {kind}, not a regular file")
        if max_bytes is not None and st.st_size > max_bytes:
            raise FileRefused(f"{name}: {st.st_size} bytes, more than {max_bytes}")
        os.set_blocking(fd, True)
        return os.fdopen(fd, "r" if text else "rb", **({"encoding": "utf-8"} if text else {}))
    except BaseException:
        os.close(fd)
        raise


def read_regular(path: str | os.PathLike | Path, max_bytes: int) -> bytes:
    """The bytes of a regular file of at most ``max_bytes`` (it may not grow past it meanwhile)."""
    with open_regular(path, max_bytes) as f:
        data = f.read(max_bytes + 1)
    if len(data) > max_bytes:
        raise FileRefused(f"{os.fspath(path)}: more than {max_bytes} bytes")
    return data

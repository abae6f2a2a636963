"""Quiet native libraries: FFmpeg inside OpenCV logs to the process's stderr (``moov atom not
found``, an encoder it cannot open, a damaged frame) on its own, ahead of the one line
perchpose says about the same thing."""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager


@contextmanager
def native_stderr_silenced() -> Iterator[None]:
    """Native libraries' writes to file descriptor 2 go nowhere while this lasts; Python's
    own ``sys.stderr`` is not touched (what Python prints in between still shows)."""
    try:
        saved = os.dup(2)
    except OSError:
        yield
        return
    try:
        with open(os.devnull, "wb") as null:
            os.dup2(null.fileno(), 2)
        yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)

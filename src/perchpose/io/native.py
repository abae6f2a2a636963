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


def opencv_reason(exc: Exception) -> str:
    """The reason an OpenCV error gives, without its source location: ``pixels <=
    CV_IO_MAX_IMAGE_PIXELS`` of ``OpenCV(5.0.0) .../loadsave.cpp:79: error: (-215:Assertion
    failed) pixels <= CV_IO_MAX_IMAGE_PIXELS in function 'validateInputImageSize'``."""
    text = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
    if "failed)" in text:
        text = text.split("failed)", 1)[1]
    return text.split(" in function", 1)[0].strip()

import os
import sys

import pytest

from perchpose.io.native import native_stderr_silenced


def test_native_writes_are_silenced_and_stderr_comes_back(
    capfd: pytest.CaptureFixture[str],
) -> None:
    with native_stderr_silenced():
        os.write(2, b"[mov @ 0x0] moov atom not found\n")
    os.write(2, b"after\n")
    sys.stderr.flush()
    assert capfd.readouterr().err == "after\n"

"""The camera stream that the sim-vehicle sends: H.264 in MPEG-TS, read back by FFmpeg as
``track`` reads a stream."""

import threading
import time
from pathlib import Path

import numpy as np
import pytest

from perchpose.errors import SourceError
from perchpose.io.sources import open_source
from perchpose.io.video_stream import H264Stream


def _frame(k: int) -> np.ndarray:
    """A gray frame whose dark square's column says its index."""
    image = np.full((240, 320), 200, np.uint8)
    image[80:160, 10 + 8 * k : 50 + 8 * k] = 20
    return image


def _square_left_px(image: np.ndarray) -> int:
    gray = image if image.ndim == 2 else image.mean(axis=2)
    return int(np.argmax(gray[120] < 110))


def test_frames_written_to_a_ts_file_decode_in_order(tmp_path: Path):
    path = tmp_path / "camera.ts"
    stream = H264Stream(str(path), 30.0, (320, 240))
    for k in range(20):
        stream.send(k, _frame(k))
        time.sleep(0.01)  # as a camera's frames come, so none is dropped
    stream.close()
    assert stream.sent + stream.dropped == 20
    assert not stream.error
    frames = [f for f in open_source(str(path), 30.0) if f.image is not None]
    assert len(frames) == stream.sent
    lefts = [_square_left_px(f.image) for f in frames]
    assert lefts == sorted(lefts)
    assert abs(lefts[0] - 10) <= 2


def test_a_reader_of_the_udp_stream_gets_its_frames(udp_port: int):
    url = f"udp://127.0.0.1:{udp_port}"
    stream = H264Stream(url, 30.0, (320, 240))

    def send() -> None:
        for k in range(90):
            stream.send(k, _frame(k % 30))
            time.sleep(1 / 30)

    sender = threading.Thread(target=send, daemon=True)
    sender.start()
    got = 0
    for frame in open_source(url, 30.0):
        got += frame.image is not None
        if got >= 10:
            break
    sender.join()
    stream.close()
    assert got >= 10


def test_a_stream_that_cannot_be_opened_says_where(tmp_path: Path):
    with pytest.raises(SourceError, match="no-such-folder"):
        H264Stream(str(tmp_path / "no-such-folder" / "camera.ts"), 30.0, (320, 240))

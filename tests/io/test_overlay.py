from pathlib import Path

import cv2
import numpy as np
import pytest

from perchpose import PerchingEstimator
from perchpose.errors import PerchposeError
from perchpose.geometry import facing_pose
from perchpose.io.overlay import OverlayWriter, draw_overlay
from perchpose.sim.render import Renderer


def test_overlay_draws_outlines_axes_and_text(renderers: dict[str, Renderer]) -> None:
    r = renderers["webcam"]
    image = r.render(facing_pose(0.0, 0.0, 0.5))
    e = PerchingEstimator(r.camera, r.target).update(image, 0.0)
    out = draw_overlay(image, e, r.camera)
    assert out.shape == (480, 640, 3)
    green = (out[:, :, 1] > 150) & (out[:, :, 0] < 80) & (out[:, :, 2] < 80)
    red = (out[:, :, 2] > 200) & (out[:, :, 1] < 80)
    assert green.sum() > 500  # outlines
    assert red.sum() > 20  # x axes
    text_band = out[440:, :300]
    assert np.any(np.all(text_band == 255, axis=2))
    # the text is drawn once, white on a darkened box: no second, black copy (a thicker
    # Hershey text advances further per glyph and read as a doubled, offset line)
    assert not np.any(np.all(text_band < 8, axis=2))


def test_overlay_video_round_trip(tmp_path: Path) -> None:
    path = tmp_path / "o.mp4"
    w = OverlayWriter(path, 30.0, (64, 48))
    for k in range(5):
        w.write(np.full((48, 64, 3), 40 * k, np.uint8))
    w.close()
    cap = cv2.VideoCapture(str(path))
    assert int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) == 5
    cap.release()
    with pytest.raises(PerchposeError, match="overlay must end in"):
        OverlayWriter(tmp_path / "o.gif", 30.0, (64, 48))


def test_an_mp4_overlay_is_h264_and_prints_nothing(
    tmp_path: Path, capfd: pytest.CaptureFixture[str]
) -> None:
    """H.264 in yuv420p (what browsers play) at the camera's rate, an odd size written one
    pixel smaller, and no FFmpeg lines on the terminal."""
    import av

    writer = OverlayWriter(tmp_path / "run.mp4", 29.97, (65, 49))
    for k in range(4):
        writer.write(np.full((49, 65, 3), 50 * k, np.uint8))
    writer.close()
    assert writer.codec == "avc1"
    with av.open(str(tmp_path / "run.mp4")) as video:
        stream = video.streams.video[0]
        assert stream.codec_context.name == "h264"
        assert (stream.width, stream.height) == (64, 48)
        assert stream.codec_context.pix_fmt == "yuv420p"
        assert float(stream.average_rate) == pytest.approx(29.97, abs=0.01)
        levels = [float(f.to_ndarray(format="gray").mean()) for f in video.decode(stream)]
    assert len(levels) == 4
    assert np.all(np.abs(np.diff(levels) - 50) < 5)
    assert capfd.readouterr().err == ""


def test_an_mp4_overlay_killed_mid_run_plays_up_to_its_last_second(tmp_path: Path) -> None:
    """A process writing 100 frames at 30 fps killed with SIGKILL before it closes the file:
    the fragmented MP4 plays every whole second written (at least 90 frames), where an MP4
    with its index at the end played none."""
    import subprocess
    import sys

    import av

    path = tmp_path / "killed.mp4"
    script = (
        "import os, signal, numpy as np\n"
        "from perchpose.io.overlay import OverlayWriter\n"
        f"w = OverlayWriter({str(path)!r}, 30.0, (160, 120))\n"
        "for k in range(100):\n"
        "    w.write(np.full((120, 160, 3), (5 * k) % 250, np.uint8))\n"
        "os.kill(os.getpid(), signal.SIGKILL)\n"
    )
    done = subprocess.run([sys.executable, "-c", script], timeout=120, check=False)
    assert done.returncode == -9
    with av.open(str(path)) as video:
        frames = sum(1 for _ in video.decode(video.streams.video[0]))
    assert frames >= 90

from pathlib import Path

import cv2
import numpy as np
import pytest

from perchpose.errors import SourceError
from perchpose.io.sources import open_source


def _write_images(folder: Path, names: list[str]) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    for k, name in enumerate(names):
        cv2.imwrite(str(folder / name), np.full((48, 64), 10 * k, np.uint8))


def test_folder_is_sorted_by_name_with_times_from_fps(tmp_path: Path) -> None:
    _write_images(tmp_path, ["b.png", "a.png", "c.jpg"])
    (tmp_path / "notes.txt").write_text("not an image")
    frames = list(open_source(str(tmp_path), fps=10))
    assert [f.name for f in frames] == ["a.png", "b.png", "c.jpg"]
    assert [f.t_s for f in frames] == [0.0, 0.1, 0.2]
    assert frames[0].image is not None
    assert frames[0].image.shape == (48, 64)


def test_glob_and_single_file(tmp_path: Path) -> None:
    _write_images(tmp_path, ["x1.png", "x2.png", "y.png"])
    assert [f.name for f in open_source(str(tmp_path / "x*.png"))] == ["x1.png", "x2.png"]
    assert len(list(open_source(str(tmp_path / "y.png")))) == 1


def test_unreadable_frame_is_reported_in_place(tmp_path: Path) -> None:
    _write_images(tmp_path, ["0.png", "2.png"])
    (tmp_path / "1.png").write_bytes(b"\x89PNG broken")
    frames = list(open_source(str(tmp_path)))
    assert [f.image is None for f in frames] == [False, True, False]
    assert "1.png: cannot read image" in frames[1].error
    assert frames[1].t_s == pytest.approx(1 / 30)


def test_video_file(tmp_path: Path) -> None:
    path = tmp_path / "v.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter.fourcc(*"MJPG"), 25.0, (64, 48))
    assert writer.isOpened()
    for k in range(7):
        writer.write(np.full((48, 64, 3), 30 * k, np.uint8))
    writer.release()
    frames = list(open_source(str(path)))
    assert len(frames) == 7
    assert frames[3].t_s == pytest.approx(3 / 25)
    assert frames[3].image is not None
    assert frames[3].image.shape == (48, 64, 3)
    assert list(open_source(str(path), fps=10))[3].t_s == pytest.approx(0.3)


@pytest.mark.parametrize(
    ("make", "message"),
    [
        (lambda p: p / "missing", "no such file or folder"),
        (lambda p: p, "holds no image files"),
        (lambda p: p / "*.png", "matches no file"),
    ],
)
def test_bad_sources(tmp_path: Path, make: object, message: str) -> None:
    with pytest.raises(SourceError, match=message):
        open_source(str(make(tmp_path)))  # type: ignore[operator]


def test_not_a_video(tmp_path: Path) -> None:
    path = tmp_path / "clip.mp4"
    path.write_bytes(b"garbage" * 10)
    with pytest.raises(SourceError, match="not a readable video"):
        open_source(str(path))


def test_bad_fps() -> None:
    with pytest.raises(SourceError, match="--fps must be a positive"):
        open_source(".", fps=-1)

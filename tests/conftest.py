"""Shared fixtures: the paper's target, preset cameras, cached renderers, rendered sequences."""

from __future__ import annotations

import fcntl
import os
import socket
import struct
import zlib
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import pytest
from numpy.typing import NDArray

os.environ.setdefault("MPLBACKEND", "Agg")

from perchpose import CameraModel, TargetSpec
from perchpose.sim.render import Renderer
from perchpose.sim.scenarios import approach
from perchpose.sim.sequence import write_sequence

SHARED_DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "opencv_charuco"


@pytest.fixture(scope="session")
def paper_target() -> TargetSpec:
    return TargetSpec.paper()


@pytest.fixture(scope="session")
def webcam() -> CameraModel:
    return CameraModel.preset("webcam")


@pytest.fixture(scope="session")
def fpv() -> CameraModel:
    return CameraModel.preset("fpv")


@pytest.fixture(scope="session")
def fpv_wide() -> CameraModel:
    return CameraModel.preset("fpv_wide")


@pytest.fixture(scope="session")
def renderers(paper_target: TargetSpec) -> dict[str, Renderer]:
    """One renderer per preset camera, built on first use (their ray tables are cached)."""

    class Lazy(dict[str, Renderer]):
        def __missing__(self, name: str) -> Renderer:
            r = Renderer(CameraModel.preset(name), paper_target)
            self[name] = r
            return r

    return Lazy()


@pytest.fixture(scope="session")
def charuco_dir() -> Path:
    if not SHARED_DATA.is_dir():
        pytest.skip(f"real photos not found at {SHARED_DATA}")
    return SHARED_DATA


def _short_approach_dir(tmp_path_factory: pytest.TempPathFactory, camera_name: str) -> Path:
    """The approach rendered once per test run: pytest-xdist's workers share the folder (the
    first to need it renders it under a lock, the others wait and read it)."""
    name = f"approach_{camera_name}"

    def render(out: Path) -> Path:
        scenario = approach(duration_s=3.0, start_z_m=0.9, dropouts=((1.0, 0.4),))
        camera = CameraModel.preset(camera_name)
        return write_sequence(scenario, camera, TargetSpec.paper(), out, seed=1, progress=False)

    if os.environ.get("PYTEST_XDIST_WORKER") is None:
        return render(tmp_path_factory.mktemp(name))
    shared = tmp_path_factory.getbasetemp().parent  # this run's, shared by its workers
    with open(shared / f"{name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        out, done = shared / name, shared / f"{name}.done"
        if not done.exists():
            render(out)
            done.touch()
    return out


@pytest.fixture(scope="session")
def approach_webcam_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A rendered 3 s approach (90 frames, a 12-frame dropout at 1.0 s) through the webcam."""
    return _short_approach_dir(tmp_path_factory, "webcam")


@pytest.fixture(scope="session")
def approach_fpv_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The same approach through the equidistant FPV camera."""
    return _short_approach_dir(tmp_path_factory, "fpv")


@pytest.fixture(scope="session")
def track_argv() -> Callable[..., list[str]]:
    """``perchpose track`` arguments: ``track_argv(frames_dir, out, *options, camera=...)``
    reads the rendered sequence in ``frames_dir`` with its own ``camera.yaml`` (or
    ``camera``), writes the track file ``out``, then the options."""

    def argv(frames_dir: Path, out: Path, *options: str, camera: str | None = None) -> list[str]:
        chosen = str(frames_dir / "camera.yaml") if camera is None else camera
        return ["track", str(frames_dir), "--camera", chosen, "--out", str(out), *options]

    return argv


def _free_port(kind: socket.SocketKind) -> int:
    """A port on 127.0.0.1 that was free a moment ago."""
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@pytest.fixture
def udp_port() -> int:
    """A free UDP port on 127.0.0.1, for a loopback MAVLink link."""
    return _free_port(socket.SOCK_DGRAM)


@pytest.fixture
def tcp_port() -> int:
    """A free TCP port on 127.0.0.1: a peer that is not there yet, or a server to start."""
    return _free_port(socket.SOCK_STREAM)


@pytest.fixture
def silent_scheduler(monkeypatch: pytest.MonkeyPatch, tcp_port: int) -> str:
    """A tcp:// address on which nothing listens, and a 1 s wait for a scheduler to answer."""
    pytest.importorskip("dask.distributed")
    from perchpose.sim import campaign

    monkeypatch.setattr(campaign, "SCHEDULER_TIMEOUT_S", 1)
    return f"tcp://127.0.0.1:{tcp_port}"


@pytest.fixture(scope="session")
def huge_png() -> bytes:
    """A small PNG whose header claims 40000 x 40000 pixels (1.6 Gpx, over OpenCV's limit)."""
    ihdr = struct.pack(">IIBBBBB", 40000, 40000, 8, 0, 0, 0, 0)

    def chunk(kind: bytes, body: bytes) -> bytes:
        return (
            struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))
        )

    idat = zlib.compress(b"\x00" * 16)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", idat) + chunk(b"IEND", b"")


Filming = Callable[[NDArray[np.uint8], np.random.Generator], NDArray[np.uint8]]


def _filmed(image: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """``image`` on a screen seen by a 640 x 480 camera: smaller, slanted, blurred, noisy."""
    h, w = image.shape
    src = np.float32([[0, 0], [w, 0], [w, h], [0, h]])
    dst = np.float32([[90, 130], [560, 100], [580, 360], [70, 380]])
    view = cv2.warpPerspective(
        image, cv2.getPerspectiveTransform(src, dst), (640, 480), borderValue=60
    )
    view = cv2.GaussianBlur(view, (0, 0), 1.2).astype(np.float64)
    view = 0.6 * view + 40 + rng.normal(0, 4, view.shape)
    return np.clip(view, 0, 255).astype(np.uint8)


@pytest.fixture
def film_screen() -> Filming:
    """A camera filming a screen: an image as the screen shows it -> the camera's frame."""
    return _filmed

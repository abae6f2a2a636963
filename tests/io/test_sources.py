import math
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from perchpose.errors import SourceError
from perchpose.io.frames import Frame
from perchpose.io.sources import LatestFrame, VideoSource, open_source
from perchpose.sim.lossy_video import encode_h264


def _write_images(folder: Path, names: list[str]) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    for k, name in enumerate(names):
        cv2.imwrite(str(folder / name), np.full((48, 64), 10 * k, np.uint8))


def test_folder_is_sorted_by_name_with_times_from_fps(tmp_path: Path) -> None:
    _write_images(tmp_path, ["b.png", "a.png", "c.jpg"])
    (tmp_path / "notes.txt").write_text("not an image")
    frames = list(open_source(str(tmp_path), fps=10))
    assert [f.name for f in frames] == ["a.png", "b.png", "c.jpg"]
    assert [f.file for f in frames] == [str(tmp_path / n) for n in ("a.png", "b.png", "c.jpg")]
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


def test_images_opencv_refuses_are_rows_and_the_rest_are_read(
    tmp_path: Path, huge_png: bytes
) -> None:
    """An empty file and a PNG that claims 1.6 Gpx (OpenCV raises, it does not return None)
    are each a row with the reason; the frames around them are read."""
    _write_images(tmp_path, ["0.png", "3.png"])
    (tmp_path / "1.png").write_bytes(b"")
    (tmp_path / "2.png").write_bytes(huge_png)
    source = open_source(str(tmp_path))
    frames = list(source)
    assert [f.image is None for f in frames] == [False, True, True, False]
    assert frames[1].error == f"{tmp_path / '1.png'}: cannot read image"
    assert frames[2].error.endswith("cannot read image (pixels <= CV_IO_MAX_IMAGE_PIXELS)")
    assert source.lost == 2


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


def test_not_a_video(tmp_path: Path, capfd: pytest.CaptureFixture[str]) -> None:
    """One error from perchpose, and no FFmpeg line ("moov atom not found") before it."""
    path = tmp_path / "clip.mp4"
    path.write_bytes(b"garbage" * 10)
    capfd.readouterr()
    with pytest.raises(SourceError, match="not a readable video"):
        open_source(str(path))
    assert capfd.readouterr().err == ""


def test_bad_fps() -> None:
    with pytest.raises(SourceError, match="--fps must be a positive"):
        open_source(".", fps=-1)


def test_numbers_in_names_sort_by_value(tmp_path: Path) -> None:
    names = [f"img_{i}.png" for i in range(12)] + ["IMG_3b.png"]
    _write_images(tmp_path, names[::-1])
    expected = [f"img_{i}.png" for i in range(4)] + ["IMG_3b.png"]
    expected += [f"img_{i}.png" for i in range(4, 12)]
    assert [f.name for f in open_source(str(tmp_path))] == expected
    assert [f.name for f in open_source(str(tmp_path / "img_*.png"))][:3] == [
        "img_0.png",
        "img_1.png",
        "img_2.png",
    ]


def _video(path: Path, frames: int, fourcc: str) -> None:
    """Frame k: noise on top (so that it compresses poorly), grey level 8 k below."""
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter.fourcc(*fourcc), 30.0, (160, 120))
    assert writer.isOpened()
    rng = np.random.default_rng(0)
    for k in range(frames):
        image = np.full((120, 160, 3), 8 * k, np.uint8)
        image[:60] = rng.integers(0, 255, (60, 160, 3), dtype=np.uint8)
        writer.write(image)
    writer.release()


def test_a_damaged_video_keeps_a_row_per_frame_and_counts_the_lost(tmp_path: Path) -> None:
    """20 kB zeroed in the middle of an MP4: the frames there are lost, the later ones still
    decode, each in its own row at its own index."""
    path = tmp_path / "v.mp4"
    _video(path, 30, "mp4v")
    data = bytearray(path.read_bytes())
    middle = len(data) // 2
    data[middle : middle + 20_000] = bytes(20_000)
    path.write_bytes(bytes(data))
    source = open_source(str(path))
    frames = list(source)
    assert [f.index for f in frames] == list(range(30))
    lost = [f for f in frames if f.image is None]
    assert 1 <= len(lost) < 15
    assert source.lost == len(lost)
    assert all("cannot be decoded" in f.error and f.file == f"{path}#{f.index}" for f in lost)
    after = [f for f in frames if f.image is not None and f.index > lost[-1].index]
    assert len(after) >= 10
    # frame k is grey 8 k below the noise (the codec darkens it by 3-5 levels): each decoded
    # frame sits at its own index, where a frame one place off would be 8 levels further off
    levels = np.array([float(f.image[80:, :].mean()) for f in after if f.image is not None])
    expected = 8.0 * np.array([f.index for f in after])
    assert np.all(np.abs(levels - expected) < 6)


def test_a_truncated_video_says_how_many_frames_it_lost(tmp_path: Path) -> None:
    path = tmp_path / "v.avi"
    _video(path, 30, "MJPG")
    data = path.read_bytes()
    path.write_bytes(data[: len(data) * 2 // 3])
    source = open_source(str(path))
    frames = list(source)
    assert len(frames) == 30
    decoded = sum(f.image is not None for f in frames)
    assert 10 <= decoded < 30
    assert source.lost == len(frames) - decoded > 0


def test_a_truncated_jpeg_is_flagged(tmp_path: Path) -> None:
    image = np.random.default_rng(1).integers(0, 255, (120, 160), dtype=np.uint8)
    ok, data = cv2.imencode(".jpg", image)
    assert ok
    (tmp_path / "a.jpg").write_bytes(data.tobytes())
    (tmp_path / "b.jpg").write_bytes(data.tobytes()[: len(data) // 2])
    a, b = open_source(str(tmp_path))
    assert a.error == ""
    assert b.image is not None  # the decoder greys the missing half out
    assert "truncated JPEG" in b.error


def _numbered_video(path: Path, count: int) -> None:
    """An MJPG video whose frame k is a flat grey of 4 k."""
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter.fourcc(*"MJPG"), 30.0, (64, 48))
    assert writer.isOpened()
    for k in range(count):
        writer.write(np.full((48, 64, 3), 4 * k, np.uint8))
    writer.release()


def test_a_live_capture_gives_the_newest_frame_and_marks_the_overtaken_stale(
    tmp_path: Path,
) -> None:
    """A real capture read as a live camera (its own thread grabs as fast as it decodes)
    behind a consumer that takes 15 ms a frame: every frame comes once, in order; those a
    newer one overtook come stale and without an image; the others are the frame their index
    says, stamped when grabbed; the end of its frames is a camera that stopped delivering."""
    path = tmp_path / "live.avi"
    _numbered_video(path, 60)
    source = VideoSource(cv2.VideoCapture(str(path)), 30.0, "camera 7", live=True)
    frames: list[Frame] = []

    def consume() -> None:
        for frame in source:
            frames.append(frame)
            if not frame.stale:
                time.sleep(0.015)

    # a camera has no end: one whose capture stops delivering is an error, after its frames
    with pytest.raises(SourceError, match="camera 7: stopped delivering frames"):
        consume()
    assert [f.index for f in frames] == list(range(60))
    stale = [f for f in frames if f.stale]
    assert stale
    assert source.stale == len(stale)
    assert all(f.image is None for f in stale)
    for f in frames:
        if not f.stale:
            assert f.image is not None
            assert abs(float(f.image.mean()) - 4 * f.index) < 3
    grabbed = [f.grabbed_s for f in frames]
    assert grabbed == sorted(grabbed)
    assert frames[0].t_s == 0.0
    assert frames[-1].t_s == pytest.approx(grabbed[-1] - grabbed[0])
    assert frames[5].file == "camera 7#5"


def test_a_slow_consumer_does_not_queue_frames(tmp_path: Path) -> None:
    """Taking one frame and stopping leaves no backlog: closing ends the grabbing thread. (The
    grabber may get ahead of this thread before its first turn: what it overtook comes first,
    stale.)"""
    path = tmp_path / "live.avi"
    _numbered_video(path, 30)
    grabber = LatestFrame(cv2.VideoCapture(str(path)))
    taken = []
    for item in grabber:
        taken.append(item)
        if item[3] is not None:
            break
    grabber.close()
    *stale, first = taken
    assert first[3] is not None
    assert all(image is None and index < first[0] for index, _, _, image, _ in stale)
    assert all(math.isnan(stamp) for _, _, stamp, _, _ in taken)  # no clock: no stamps
    assert not grabber.running


def test_files_are_stamped_when_read(tmp_path: Path) -> None:
    _write_images(tmp_path, ["a.png", "b.png"])
    before = time.monotonic()
    frames = list(open_source(str(tmp_path)))
    assert before <= frames[0].grabbed_s <= frames[1].grabbed_s <= time.monotonic()


class _Server:
    """An HTTP server on loopback that serves ``folder`` ``times`` times, then answers 404: a
    network stream that drops, comes back once, then stays down."""

    def __init__(self, folder: Path, times: int) -> None:
        import functools
        import http.server
        import threading

        served = self.served = [0]
        agents = self.agents = []

        class Handler(http.server.SimpleHTTPRequestHandler):
            def do_GET(self) -> None:
                agents.append(self.headers.get("User-Agent", ""))
                if served[0] >= times:
                    self.send_error(404)
                    return
                served[0] += 1
                super().do_GET()

            def log_message(self, *args: object) -> None:
                pass

        self.httpd = http.server.ThreadingHTTPServer(
            ("127.0.0.1", 0), functools.partial(Handler, directory=str(folder))
        )
        self.port = self.httpd.server_address[1]
        threading.Thread(target=self.httpd.serve_forever, daemon=True).start()

    def close(self) -> None:
        self.httpd.shutdown()
        self.httpd.server_close()


def test_a_network_stream_is_read_live_and_reopened_when_it_drops(tmp_path: Path) -> None:
    """http:// through OpenCV's FFmpeg backend: every frame of the first connection, then,
    after the stream drops, every frame of the second (one reconnect); once the stream stays
    down past reconnect_for_s the source ends with an error that says so (a run on a stream
    lost for good does not end as if it had finished). Indices and grab times go on across
    the drop."""
    _numbered_video(tmp_path / "v.avi", 20)
    server = _Server(tmp_path, times=2)
    frames = []
    try:
        source = open_source(f"http://127.0.0.1:{server.port}/v.avi")
        assert isinstance(source, VideoSource)
        assert source.live
        source.reconnect_for_s = 1.0
        with pytest.raises(SourceError, match="dropped and did not come back within 1 s"):
            frames.extend(source)
    finally:
        server.close()
    assert server.served == [2]
    assert source.reconnects == 1
    assert [f.index for f in frames] == list(range(40))
    assert all(f.file == f"http://127.0.0.1:{server.port}/v.avi#{f.index}" for f in frames)
    grabbed = [f.grabbed_s for f in frames]
    assert grabbed == sorted(grabbed)
    # each frame taken (not overtaken: stale ones have no image) shows its own video frame,
    # the second connection starting the video again at index 20
    shown = [(f.index, round(float(f.image.mean()) / 4)) for f in frames if f.image is not None]
    assert shown
    assert all(value == index % 20 for index, value in shown)


def test_a_stream_gets_the_ffmpeg_options_opencv_users_set(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """OPENCV_FFMPEG_CAPTURE_OPTIONS (``key;value|key;value``, as OpenCV reads it) reaches
    FFmpeg: here the User-Agent an http:// stream is asked with."""
    _numbered_video(tmp_path / "v.avi", 5)
    server = _Server(tmp_path, times=1)
    monkeypatch.setenv("OPENCV_FFMPEG_CAPTURE_OPTIONS", "video_codec;h264|user_agent;perch-7")
    try:
        source = open_source(f"http://127.0.0.1:{server.port}/v.avi")
        assert isinstance(source, VideoSource)
        source.capture.release()
    finally:
        server.close()
    assert server.agents[0] == "perch-7"


def test_a_stream_that_never_answers_is_one_clear_error(tcp_port: int) -> None:
    # nothing listens on tcp_port
    with pytest.raises(SourceError, match=rf"http://127.0.0.1:{tcp_port}/x.avi: cannot open"):
        open_source(f"http://127.0.0.1:{tcp_port}/x.avi")


def test_a_udp_stream_that_loses_datagrams_flags_what_it_spoils(
    tmp_path: Path, udp_port: int, monkeypatch: pytest.MonkeyPatch
) -> None:
    """An H.264 camera's MPEG-TS over udp:// on loopback (a key frame every 10 frames), with
    three datagrams of 7 TS packets lost on the way: the frames they spoil come flagged, and
    every frame that is not flagged is exactly a frame the camera sent."""
    import socket
    import threading

    from perchpose.io import sources

    images = []
    for k in range(60):
        image = np.zeros((120, 160, 3), np.uint8)
        image[:, :, 1] = np.linspace(0, 200, 160, dtype=np.uint8)[None, :]
        image[40:80, 10 + 2 * k : 50 + 2 * k] = 255
        images.append(image)
    ts = encode_h264(images, tmp_path / "camera.ts", gop=10)
    sent = {f.index: f.image for f in open_source(str(ts))}
    assert len(sent) == 60
    data = ts.read_bytes()
    datagrams = [data[i : i + 1316] for i in range(0, len(data), 1316)]
    lost = {len(datagrams) * k // 4 for k in (1, 2, 3)}

    def send() -> None:
        time.sleep(0.3)  # the reader binds the port first
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as out:
            for k, datagram in enumerate(datagrams):
                if k not in lost:
                    out.sendto(datagram, ("127.0.0.1", udp_port))
                time.sleep(0.002)

    monkeypatch.setattr(sources, "STREAM_TIMEOUT_MS", 1000)
    sender = threading.Thread(target=send, daemon=True)
    sender.start()
    source = open_source(f"udp://127.0.0.1:{udp_port}")
    source.reconnect_for_s = 0.5
    frames = []
    with pytest.raises(SourceError, match="did not come back"):
        frames.extend(source)
    sender.join()
    shown = [f for f in frames if f.image is not None]
    assert len(shown) >= 30
    flagged = [f for f in shown if f.damaged]
    assert flagged
    assert all("not measured" in f.error for f in flagged)
    for f in shown:
        assert f.image is not None
        nearest = min(np.abs(f.image.astype(int) - s.astype(int)).max() for s in sent.values())
        assert f.damaged or nearest == 0, f.index
    # the stream mends at the next key frame: whole frames come after each flagged run
    assert not shown[-1].damaged


class _V4l2Camera:
    """A V4L2 camera as OpenCV's V4L2 backend shows it, standing in for the device: a real
    capture's frames, and after each grab ``CAP_PROP_POS_MSEC`` is the buffer's stamp, in ms
    on the kernel's monotonic clock (``delay_s`` before the grab), or on the wall clock where
    ``wall_clock`` (a driver that stamps with it)."""

    def __init__(self, capture: cv2.VideoCapture, delay_s: float, wall_clock: bool) -> None:
        self._capture = capture
        self.delay_s = delay_s
        self.wall_clock = wall_clock
        self.stamps_s: list[float] = []

    def getBackendName(self) -> str:  # OpenCV's names
        return "V4L2"

    def isOpened(self) -> bool:
        return self._capture.isOpened()

    def grab(self) -> bool:
        time.sleep(0.01)  # a frame every 10 ms at most
        ok = self._capture.grab()
        clock = time.time if self.wall_clock else time.monotonic
        self.stamps_s.append(clock() - self.delay_s)
        return ok

    def retrieve(self) -> tuple[bool, object]:
        return self._capture.retrieve()

    def get(self, prop: int) -> float:
        if prop == cv2.CAP_PROP_POS_MSEC:
            return self.stamps_s[-1] * 1000.0 if self.stamps_s else 0.0
        return float(self._capture.get(prop))

    def set(self, prop: int, value: float) -> bool:
        return True

    def release(self) -> None:
        self._capture.release()


@pytest.mark.parametrize("wall_clock", [False, True])
def test_a_v4l2_camera_is_dated_by_its_buffer_stamps(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, wall_clock: bool
) -> None:
    """A camera on OpenCV's V4L2 backend is dated by the kernel's buffer stamp (the camera
    latency then counts back from it); stamps on another clock are refused, and the grab
    dates those frames."""
    _numbered_video(tmp_path / "v.avi", 20)
    cameras: list[_V4l2Camera] = []
    real = cv2.VideoCapture

    def open_camera(index: object) -> _V4l2Camera:
        cameras.append(_V4l2Camera(real(str(tmp_path / "v.avi")), 0.025, wall_clock))
        return cameras[-1]

    monkeypatch.setattr(cv2, "VideoCapture", open_camera)
    source = open_source("0")
    frames = []
    with pytest.raises(SourceError, match="stopped delivering"):
        frames.extend(f for f in source if not f.stale)
    assert len(frames) >= 5
    assert source.clock is not None
    assert source.clock.name == "v4l2"
    if wall_clock:
        assert all(f.clock == "" and f.dated_s == f.grabbed_s for f in frames)
        assert source.clock.refused >= len(frames)
        return
    stamps_s = cameras[0].stamps_s  # by grab, as the frames' indices count them
    for f in frames:
        assert f.clock == "v4l2"
        assert f.stamped_s == pytest.approx(stamps_s[f.index], abs=1e-6)
        assert f.dated_s == f.stamped_s
        assert 0.02 < f.grabbed_s - f.stamped_s < 1.0


def test_a_stream_is_dated_by_its_presentation_times(udp_port: int) -> None:
    """A live H.264 stream over UDP whose frames leave the sender up to 60 ms late (a network
    and an encoder that jitter; every tenth on time): each frame's stamp is its presentation
    time mapped to this host's clock by the smallest delay seen, so once an on-time frame has
    come the stamps keep the sender's 1/30 s spacing, where the grabs keep the jitter."""
    import threading

    from perchpose.io.video_stream import H264Stream

    url = f"udp://127.0.0.1:{udp_port}"
    stream = H264Stream(url, 30.0, (160, 120))
    jitter_s = np.random.default_rng(2).uniform(0.0, 0.060, 300)
    jitter_s[::10] = 0.0
    start = time.monotonic() + 0.3
    stop = threading.Event()

    def send() -> None:
        for k in range(300):  # 10 s: the reader (which takes a while to join) stops first
            if stop.wait(max(0.0, start + k / 30.0 + jitter_s[k] - time.monotonic())):
                return
            image = np.full((120, 160), 8 + 8 * (k % 30), np.uint8)
            image[:, 80:] = 8 + 8 * (k // 30)  # the frame's number, in two halves
            stream.send(k, image)

    sender = threading.Thread(target=send, daemon=True)
    sender.start()
    frames = []
    try:
        for frame in open_source(url, 30.0):
            if frame.image is not None:
                frames.append(frame)
            if len(frames) >= 90:
                break
    finally:
        stop.set()
        sender.join()
        stream.close()
    assert all(f.clock == "stream" and f.stamped_s <= f.grabbed_s for f in frames)
    sent = np.array(
        [
            round(f.image[:, 8:72].mean() / 8 - 1) + 30 * round(f.image[:, 88:152].mean() / 8 - 1)
            for f in frames
            if f.image is not None
        ]
    )
    stamped = np.array([f.stamped_s for f in frames]) - sent / 30.0
    grabbed = np.array([f.grabbed_s for f in frames]) - sent / 30.0
    # the reader joins with a backlog (what FFmpeg read while it probed the stream), which it
    # drains faster than real time; in the last second the stamps' spacing is the sender's to
    # within a few ms of this machine's own scheduling
    assert np.ptp(stamped[-30:]) < 0.010
    assert np.std(grabbed[-30:]) > 0.010

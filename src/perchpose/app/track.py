"""Tracking a frame source into a pose file (the ``perchpose track`` command): ``run`` takes
what the command is asked for (``TrackOptions``) and returns what it did (``TrackSummary``);
``track`` is the loop over the frames, for an estimator built elsewhere."""

from __future__ import annotations

import math
import sys
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Protocol

import numpy as np
from numpy.typing import NDArray
from tqdm import tqdm

from perchpose.app.inputs import load_camera, load_target
from perchpose.app.links import LinkOptions, vehicle_links
from perchpose.camera import CameraModel
from perchpose.control.time_offset import TimeOffset
from perchpose.errors import ImageError, PerchposeError
from perchpose.estimator import PerchingEstimator
from perchpose.io.frames import TARGET_FRAME, Frame, FrameSource, Stamp
from perchpose.io.outputs import open_track_writer
from perchpose.io.overlay import OverlayWriter, check_overlay_path, draw_overlay
from perchpose.io.sinks import estimate_row, offset_columns
from perchpose.io.sources import is_live, open_source
from perchpose.target import TargetSpec
from perchpose.values import Estimate
from perchpose.warmup import warm_up


@dataclass(frozen=True)
class TrackSummary:
    """What a tracking run did."""

    frames: int
    valid: int
    bad_frames: int
    stage_counts: dict[int, int]
    mean_ms: float
    out: Path
    stale_frames: int = 0
    budget_frames: int = 0
    p95_latency_ms: float = math.nan
    damaged_frames: int = 0
    # the frames with an image each clock dated (``Frame.clock``: "" the grab), live sources only
    dated: dict[str, int] = field(default_factory=dict)


class _Tally:
    """Counts of a tracking run as its frames come."""

    def __init__(self) -> None:
        self.frames = self.valid = self.bad = self.stale = self.budget = self.damaged = 0
        self.stage_counts = {0: 0, 1: 0, 2: 0, 3: 0}
        self.total_ms = 0.0
        self.latencies_ms: list[float] = []
        self.dated: dict[str, int] = {}

    def add(self, estimate: Estimate | None, error: str, frame: Frame) -> None:
        self.frames += 1
        self.stale += int(frame.stale)
        self.damaged += int(frame.damaged)
        self.bad += int(bool(error) and not frame.stale and not frame.damaged)
        if frame.image is not None and math.isfinite(frame.grabbed_s):
            self.dated[frame.clock] = self.dated.get(frame.clock, 0) + 1
        if estimate is not None:
            self.valid += int(estimate.valid)
            self.stage_counts[estimate.stage] += 1
            self.total_ms += estimate.timings.total_ms
            self.budget += int(bool(estimate.skipped))
            if math.isfinite(estimate.latency_s):
                self.latencies_ms.append(estimate.latency_s * 1e3)
        else:
            self.stage_counts[0] += 1

    def summary(self, out: Path) -> TrackSummary:
        processed = max(1, self.frames - self.bad - self.stale - self.damaged)
        latencies = sorted(self.latencies_ms)
        p95 = (
            latencies[min(len(latencies) - 1, int(0.95 * len(latencies)))]
            if latencies
            else math.nan
        )
        return TrackSummary(
            self.frames,
            self.valid,
            self.bad,
            self.stage_counts,
            self.total_ms / processed,
            out,
            self.stale,
            self.budget,
            p95,
            self.damaged,
            dict(self.dated),
        )


class _Overlay:
    """The overlay video, opened at the first overlay (its size)."""

    def __init__(self, path: str | Path | None, fps: float) -> None:
        self.path, self.fps = path, fps
        self.video: OverlayWriter | None = None

    def write(self, picture: NDArray[np.uint8] | None) -> None:
        if self.path is None or picture is None:
            return
        if self.video is None:
            h, w = picture.shape[:2]
            self.video = OverlayWriter(self.path, self.fps, (w, h))
        self.video.write(picture)

    def close(self) -> None:
        if self.video is not None:
            self.video.close()


STALE = "stale: dropped unprocessed for a newer frame"


class FrameView(Protocol):
    """Something that shows each frame as it is tracked (``perchpose.io.view.LiveView``);
    ``wants_overlay`` whether it would show an overlay drawn now."""

    @property
    def wants_overlay(self) -> bool: ...

    def publish(
        self, stamp: Stamp, estimate: Estimate | None, overlay: NDArray[np.uint8] | None
    ) -> None: ...


class Pacer:
    """Replays a recording at ``rate`` times the speed its time stamps say (1: as recorded):
    ``wait(t_s)`` returns once the frame at ``t_s`` is due, counted from the first frame.
    A frame already late is not waited for, and the replay does not hurry to catch up."""

    def __init__(self, rate: float) -> None:
        if not (math.isfinite(rate) and rate > 0):
            raise PerchposeError(f"--rate must be a positive number, got {rate:g}")
        self.rate = rate
        self._start: tuple[float, float] | None = None  # (t_s, monotonic) of the first frame

    def wait(self, t_s: float) -> None:
        now = time.monotonic()
        if self._start is None:
            self._start = (t_s, now)
            return
        t0_s, wall0_s = self._start
        due = wall0_s + (t_s - t0_s) / self.rate
        if due > now:
            time.sleep(due - now)


MAX_CAMERA_LATENCY_S = 2.0  # beyond this no camera chain perches a vehicle


def _with_latency(estimate: Estimate, frame: Frame, camera_latency_s: float) -> Estimate:
    """``estimate`` with the moment its frame was grabbed, its capture time (the camera
    latency before the source's own stamp, or before the grab where it has none:
    ``Frame.dated_s``) as the latency before the grab, and the time from the capture to now."""
    if not math.isfinite(frame.grabbed_s):
        return estimate
    captured_s = frame.dated_s - camera_latency_s
    return replace(
        estimate,
        latency_s=time.monotonic() - captured_s,
        grabbed_s=frame.grabbed_s,
        camera_latency_s=frame.grabbed_s - captured_s,
    )


def _with_bar(frames: FrameSource, progress: bool) -> Iterator[Frame]:
    """``frames`` behind a progress bar on stderr (none without ``progress``)."""
    bar = tqdm(
        frames,
        total=frames.count,
        desc="track",
        unit="frame",
        disable=not progress,
        file=sys.stderr,
        leave=False,
    )
    yield from bar


def _measured(
    estimator: PerchingEstimator,
    frame: Frame,
    description: str,
    first: bool,
    camera_latency_s: float = 0.0,
) -> tuple[Estimate | None, str]:
    """The estimate of ``frame`` (None without one) and what went wrong with it. A frame of
    the wrong size is an error for the ``first`` frame measured (every frame would be)
    and a flagged row after it."""
    if frame.stale:
        return None, STALE
    if frame.image is None or frame.damaged:
        return None, frame.error
    try:
        grey = estimator.camera.check_image(frame.image, f"{description}: {frame.name}")
        estimate = estimator.update(grey, frame.t_s)
        return _with_latency(estimate, frame, camera_latency_s), frame.error
    except ImageError as exc:
        if first:
            raise
        return None, str(exc)


def track(
    source: str,
    estimator: PerchingEstimator,
    out: str | Path,
    *,
    fps: float | None = None,
    overlay: str | Path | None = None,
    progress: bool = True,
    on_frame: Sequence[Callable[[Estimate | None, float], None]] = (),
    image_topic: str | None = None,
    view: FrameView | None = None,
    rate: float | None = None,
    camera_frame: str | None = None,
    target_frame: str = TARGET_FRAME,
    camera_latency_s: float = 0.0,
    time_offset: Callable[[], TimeOffset | None] = lambda: None,
) -> TrackSummary:
    """Run ``estimator`` (its camera and target) over every frame of ``source`` and write one
    row per frame to ``out``; each estimate carries its latency from the frame's grab.

    ``image_topic``: the images' topic when ``source`` is a ROS bag (``perchpose.io.ros.rosbag``).
    ``view``: a live view (``perchpose.io.view.LiveView``) that gets every frame with its
    overlay. ``rate``: replay a recording at this many times the speed of its time stamps
    (``Pacer``; None: as fast as it decodes). ``camera_frame``: the camera's frame id in bags
    and the live view (default: the image's own, else ``camera``); ``target_frame``: the
    target's. ``camera_latency_s``: a live source's latency (measured by the user with
    ``perchpose latency``): each frame was captured that long before its source's own stamp
    (a V4L2 buffer's, a stream's presentation time: ``Frame.dated_s``), or before its grab
    where it has none (``Estimate.captured_s``).
    A live camera is grabbed on a thread of its own and the estimator always takes the newest
    frame: a frame overtaken before it was taken gets an invalid row saying it was stale (no
    warning each; the summary counts them).

    A frame that cannot be read or has the wrong size gets an invalid row and a warning on
    stderr; the run goes on. A video frame that decoded but rests on damaged data
    (``Frame.damaged``: it decoded with errors, or is predicted from such a frame or a missing
    one) is drawn but not measured: an invalid row that says why, and one warning where a run
    of them starts. The first frame having a size other than the calibration's is an
    error, since then every frame would be. Each of ``on_frame`` (vehicle links) is called once
    per frame with the estimate (None for an unreadable frame) and the frame's time, as soon
    as it is made (before the overlay and the row); ``time_offset`` gives the flying
    controller's estimate of the camera-to-vehicle time offset for the rows
    (``time_offset_ms``, ``time_offset_sigma_ms``).
    """
    if overlay is not None:
        check_overlay_path(overlay)
    camera, target = estimator.camera, estimator.target
    frames = open_source(source, fps, camera.size, image_topic=image_topic)
    if rate is not None and frames.live:
        raise PerchposeError(
            f"{frames.description}: --realtime and --rate replay recordings; a live source "
            "already runs in real time"
        )
    if not (math.isfinite(camera_latency_s) and 0.0 <= camera_latency_s <= MAX_CAMERA_LATENCY_S):
        raise PerchposeError(
            f"--camera-latency-ms must be 0 to {MAX_CAMERA_LATENCY_S * 1000:g}, got "
            f"{camera_latency_s * 1000:g}"
        )
    if camera_latency_s and not frames.live:
        raise PerchposeError(
            f"{frames.description}: --camera-latency-ms is for a live camera or stream, whose "
            "frames are stamped when grabbed; a recording's times are its own"
        )
    pacer = None if rate is None else Pacer(rate)
    video = _Overlay(overlay, frames.fps)
    writer = open_track_writer(out, target, target_frame)
    # the overlay is drawn once a frame, for whichever of its users there are
    draw = overlay is not None or writer.wants_overlay
    tally = _Tally()
    first_good = True
    damaged_before = False
    try:
        for read in _with_bar(frames, progress):
            frame = read
            if pacer is not None:
                pacer.wait(frame.t_s)
                frame = replace(frame, grabbed_s=time.monotonic())
            stamp = Stamp.of(frame, camera_frame)
            estimate, error = _measured(
                estimator, frame, frames.description, first_good, camera_latency_s
            )
            for hook in () if frame.stale else on_frame:  # no news in a frame not looked at
                hook(estimate, frame.t_s)  # the vehicle first: nothing else waits on it
            first_good = first_good and (frame.image is None or frame.damaged)
            if error and not frame.stale and not (frame.damaged and damaged_before):
                more = " (and the frames after it until one decodes whole)" * frame.damaged
                print(f"warning: {error}{more}", file=sys.stderr)
            damaged_before = frame.damaged
            picture = None
            if frame.image is not None and (draw or (view is not None and view.wants_overlay)):
                note = f"t {frame.t_s:.2f} s" + "  damaged: not measured" * frame.damaged
                picture = draw_overlay(frame.image, estimate, camera, note=note)
            row = estimate_row(frame.index, frame.t_s, estimate, target, error, frame.file)
            row.update(offset_columns(time_offset()))
            writer.write_frame(row, estimate, stamp, picture)
            tally.add(estimate, error, frame)
            if view is not None and not frame.stale:
                view.publish(stamp, estimate, picture)
            video.write(picture)
    finally:
        writer.close()
        video.close()
    if tally.frames == 0:
        raise PerchposeError(f"{frames.description}: the source gave no frames")
    return tally.summary(Path(out))


@dataclass(frozen=True)
class TrackOptions:
    """What ``perchpose track`` is asked for. ``camera_file``: a calibration file or
    ``preset:NAME``; None only for a ROS bag, whose ``camera_info_topic`` (or only CameraInfo
    topic) gives the camera. ``sigmas_file``: the paper's fusion with these weights instead of
    the joint pose. ``view``: serve the live view on ``view_port`` (``view_origins`` also let
    in). ``links``: the vehicle links to fly on. The rest as ``track`` takes them."""

    source: str
    out: str
    camera_file: str | None = None
    camera_info_topic: str | None = None
    image_topic: str | None = None
    target_file: str | None = None
    fps: float | None = None
    overlay: str | None = None
    sigmas_file: str | None = None
    budget_ms: float | None = None
    view: bool = False
    view_port: int = 8765
    view_origins: tuple[str, ...] = ()
    rate: float | None = None
    camera_frame: str | None = None
    target_frame: str = TARGET_FRAME
    links: LinkOptions = field(default_factory=LinkOptions)
    progress: bool = True
    camera_latency_s: float = 0.0


def _camera(options: TrackOptions) -> CameraModel:
    """The camera of ``camera_file``, or of a bag's CameraInfo topic."""
    from perchpose.io.ros.rosbag import camera_from_bag, is_bag

    if options.camera_file is not None:
        return load_camera(options.camera_file)
    if is_bag(options.source):
        return camera_from_bag(options.source, options.camera_info_topic)
    raise PerchposeError(f"{options.source}: give --camera (only a ROS bag brings its own)")


@contextmanager
def _live_view(
    options: TrackOptions, target: TargetSpec, report: Callable[[str], None]
) -> Iterator[FrameView | None]:
    """The live view when asked for (imported only then), closed at the end."""
    if not options.view:
        yield None
        return
    from perchpose.io.view import LiveView

    view = LiveView(
        target,
        port=options.view_port,
        allowed_origins=options.view_origins,
        report=report,
        target_frame=options.target_frame,
    )
    report(f"live view for Foxglove at ws://127.0.0.1:{view.port}")
    try:
        yield view
    finally:
        view.close()


def run(options: TrackOptions, report: Callable[[str], None]) -> TrackSummary:
    """Track ``options.source`` as ``perchpose track`` does: the camera, target and estimator
    it names, the live view and vehicle links it asks for (opened around the frames, closed
    after them); ``report`` gets the lines a user should read."""
    flies = options.links.flies
    if flies is not None and options.rate != 1.0 and not is_live(options.source):
        raise PerchposeError(
            f"{options.source}: a recording flies a live vehicle ({flies}) only paced as it "
            "was recorded: add --realtime"
        )
    camera = _camera(options)
    target = load_target(options.target_file)
    estimator = PerchingEstimator.configured(
        camera, target, sigmas_file=options.sigmas_file, budget_ms=options.budget_ms
    )
    if options.overlay is not None:
        check_overlay_path(options.overlay)  # before any vehicle link takes over
    with (
        _live_view(options, target, report) as live,
        vehicle_links(target, options.links, report) as links,
    ):
        hooks = links.hooks
        if is_live(options.source) or options.rate is not None or hooks or live is not None:
            # in real time no frame may wait on a compile: every kernel is built before the
            # first (after the links opened, so that a wrong link is said at once)
            done = warm_up(target, [camera])
            if not done.already:
                report(done.describe())
        return track(
            options.source,
            estimator,
            options.out,
            fps=options.fps,
            overlay=options.overlay,
            progress=options.progress,
            on_frame=hooks,
            time_offset=links.time_offset,
            image_topic=options.image_topic,
            view=live,
            rate=options.rate,
            camera_frame=options.camera_frame,
            target_frame=options.target_frame,
            camera_latency_s=options.camera_latency_s,
        )

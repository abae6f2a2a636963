"""perchpose as a ROS 2 node (``perchpose ros2``; rclpy, from a ROS 2 install or the ``ros2``
extra's wheels).

Subscribes (remappable) to ``image_raw`` (``sensor_msgs/Image``; with ``image_transport:
compressed``, ``image_raw/compressed``), reliable where every publisher of it is reliable and
best effort otherwise, as ``ros2 topic echo`` matches them (``perchpose.io.ros.transport``; a
``qos_overrides`` parameter still decides), and to ``camera_info`` (sensor-data QoS);
publishes, each stamped with its image's exact stamp in its image's frame id (or
``camera_frame``):
- ``~/pose`` (``/perchpose/pose``): ``geometry_msgs/PoseWithCovarianceStamped``, the target in
  the camera frame with ``Estimate.covariance``, on frames with a valid pose;
- ``~/track``: ``std_msgs/String``, the frame's track row as JSON (stage, markers,
  ``predicted``, ``age_s``, ``measured``, ``latency_ms``), every frame taken;
- ``~/overlay/compressed``: ``sensor_msgs/CompressedImage`` (JPEG) with ``publish_overlay``;
- ``/tf``: camera frame -> ``target_frame``, where ``tf2_msgs`` is importable;
- ``/diagnostics``: ``diagnostic_msgs/DiagnosticArray`` every ``diagnostics_period_s`` (rate,
  latency percentiles, stage counts, drops, refusals, frames lost in transport: gaps in the
  header stamps against the camera's period), where ``diagnostic_msgs`` is importable.

Images are taken newest first on a thread of their own: one that arrives while another waits
replaces it (counted as dropped), so the node never works through a queue of stale frames. The
camera is ``camera_file`` when given, else the first ``CameraInfo``; an image or a CameraInfo of
another size is refused, logged once per size.
"""

from __future__ import annotations

import importlib
import json
import math
import sys
import threading
import time
from dataclasses import dataclass, fields, replace
from pathlib import Path
from typing import Any

import numpy as np

from perchpose.camera import CameraModel
from perchpose.errors import PerchposeError, SourceError
from perchpose.estimator import PerchingEstimator
from perchpose.io.frames import CAMERA_FRAME, Stamp
from perchpose.io.overlay import draw_overlay, encode_jpeg
from perchpose.io.ros.messages import camera_info_fields, header_stamp_ns, image_of, pose_fields
from perchpose.io.ros.transport import BEST_EFFORT, RELIABLE, StampGaps, matching_reliability
from perchpose.io.sinks import estimate_row, track_json
from perchpose.safe_yaml import load as load_yaml
from perchpose.target import TargetSpec
from perchpose.values import Estimate
from perchpose.warmup import warm_up

NODE_NAME = "perchpose"
PARAMS_FILE = Path(__file__).with_name("perchpose.params.yaml")
_MODULES = {
    "rclpy": "rclpy",
    "qos": "rclpy.qos",
    "executors": "rclpy.executors",
    "overriding": "rclpy.qos_overriding_options",
    "sensor": "sensor_msgs.msg",
    "geometry": "geometry_msgs.msg",
    "std": "std_msgs.msg",
    "builtin": "builtin_interfaces.msg",
}
_OPTIONAL = {"tf": "tf2_msgs.msg", "diagnostic": "diagnostic_msgs.msg"}


def missing_rclpy(
    module: str, python: tuple[int, int] | None = None, platform: str | None = None
) -> str:
    """What to do when rclpy (or a message package) is not importable: the ``ros2`` extra's
    wheels exist only for ROS 2 Jazzy on Python 3.11 under Linux, and elsewhere the extra
    installs nothing, without a word."""
    python = python or (sys.version_info.major, sys.version_info.minor)
    platform = platform or sys.platform
    here = f"Python {python[0]}.{python[1]} on {platform}"
    if python != (3, 11) or platform != "linux":
        return (
            f"perchpose ros2 needs rclpy ({module} is missing): source a ROS 2 install whose "
            f"Python this is (Jazzy's is 3.12); the 'ros2' extra's wheels are for Python 3.11 "
            f"on Linux only and install nothing on {here}"
        )
    return (
        f"perchpose ros2 needs rclpy ({module} is missing): source a ROS 2 install, or "
        "pip install 'perchpose[ros2]' (ROS 2 Jazzy's wheels for Python 3.11)"
    )


def _ros() -> dict[str, Any]:
    """rclpy and the message packages the node needs; the optional ones where importable."""
    found: dict[str, Any] = {}
    try:
        for key, name in _MODULES.items():
            found[key] = importlib.import_module(name)
    except ImportError as exc:
        raise PerchposeError(missing_rclpy(exc.name or name)) from exc
    for key, name in _OPTIONAL.items():
        try:
            found[key] = importlib.import_module(name)
        except ImportError:
            found[key] = None
    return found


RESTART_BACK_S = 1.0  # an image stamp this far behind the last: the camera started over
LOST_WARN = 0.05  # a share of images lost in transport that the diagnostics warn of
MATCH_PERIOD_S = 0.5  # how often the publishers are looked for until the first is found


@dataclass(frozen=True)
class NodeSettings:
    """The node's parameters (``perchpose.params.yaml`` holds their defaults, and is the file
    to copy for ``--ros-args --params-file``)."""

    target_file: str = ""
    camera_file: str = ""
    camera_frame: str = ""
    target_frame: str = "target"
    sigmas_file: str = ""
    budget_ms: float = 0.0
    image_transport: str = "raw"
    publish_overlay: bool = False
    diagnostics_period_s: float = 1.0

    def __post_init__(self) -> None:
        if self.image_transport not in ("raw", "compressed"):
            raise PerchposeError(
                f"parameter image_transport: 'raw' or 'compressed', got {self.image_transport!r}"
            )
        if not (math.isfinite(self.budget_ms) and self.budget_ms >= 0):
            raise PerchposeError(f"parameter budget_ms: 0 (none) or more, got {self.budget_ms}")
        if not (math.isfinite(self.diagnostics_period_s) and self.diagnostics_period_s > 0):
            raise PerchposeError(
                f"parameter diagnostics_period_s: positive, got {self.diagnostics_period_s}"
            )

    @staticmethod
    def defaults() -> dict[str, Any]:
        """The shipped parameters file's values, by name."""
        data = load_yaml(PARAMS_FILE.read_text(encoding="utf-8"))
        values = data[NODE_NAME]["ros__parameters"]
        names = {f.name for f in fields(NodeSettings)}
        if set(values) != names:
            raise PerchposeError(f"{PARAMS_FILE}: expected the parameters {sorted(names)}")
        return dict(values)

    def estimator(self, camera: CameraModel, target: TargetSpec) -> PerchingEstimator:
        """The estimator these settings ask for (empty and 0 mean none)."""
        return PerchingEstimator.configured(
            camera, target, sigmas_file=self.sigmas_file or None, budget_ms=self.budget_ms or None
        )


class LatestImage:
    """One slot for the newest image message: ``put`` replaces what waits there (returning
    True when it dropped one), ``take`` waits for it."""

    def __init__(self) -> None:
        self._ready = threading.Condition()
        self._item: tuple[Any, float] | None = None
        self.closed = False

    def put(self, msg: Any, received_s: float) -> bool:
        with self._ready:
            dropped = self._item is not None
            self._item = (msg, received_s)
            self._ready.notify()
        return dropped

    def take(self, timeout_s: float) -> tuple[Any, float] | None:
        with self._ready:
            if self._item is None and not self.closed:
                self._ready.wait(timeout_s)
            item, self._item = self._item, None
        return item

    def close(self) -> None:
        with self._ready:
            self.closed = True
            self._ready.notify_all()


class NodeStats:
    """What the node did since the last diagnostics: images in, taken, dropped for a newer one,
    refused; stages; latencies from an image's arrival to its outputs."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.total_taken = 0
        self._reset(time.monotonic())

    def _reset(self, now_s: float) -> None:
        self.since_s = now_s
        self.received = self.taken = self.dropped = self.refused = self.lost = 0
        self.stages = {0: 0, 1: 0, 2: 0, 3: 0}
        self.latencies_ms: list[float] = []

    def took(self, estimate: Estimate, latency_s: float) -> None:
        with self.lock:
            self.taken += 1
            self.total_taken += 1
            self.stages[estimate.stage] += 1
            self.latencies_ms.append(latency_s * 1e3)

    def count(self, name: str, n: int = 1) -> None:
        with self.lock:
            setattr(self, name, getattr(self, name) + n)

    def report(self, waiting_for: str) -> tuple[int, str, dict[str, str]]:
        """(level 0 OK / 1 WARN / 2 ERROR, message, values) since the last report, which
        starts a new period."""
        with self.lock:
            now = time.monotonic()
            period = max(now - self.since_s, 1e-9)
            latencies = np.array(self.latencies_ms) if self.latencies_ms else np.array([math.nan])
            values = {
                "rate_hz": f"{self.taken / period:.2f}",
                "received_hz": f"{self.received / period:.2f}",
                "latency_p50_ms": f"{np.percentile(latencies, 50):.1f}",
                "latency_p95_ms": f"{np.percentile(latencies, 95):.1f}",
                "dropped": str(self.dropped),
                "refused": str(self.refused),
                "lost_in_transport": str(self.lost),
            } | {f"stage_{k}": str(v) for k, v in self.stages.items()}
            valid = self.taken - self.stages[0]
            if waiting_for:
                level, message = 1, f"waiting for {waiting_for}"
            elif self.refused:
                plural = "s" if self.refused != 1 else ""
                level, message = 2, f"{self.refused} image{plural} refused (see the log)"
            elif self.lost > LOST_WARN * (self.received + self.lost):
                level = 1
                message = (
                    f"{self.lost} of {self.received + self.lost} images lost in transport "
                    "(gaps in their stamps)"
                )
            elif self.taken and not valid:
                level, message = 1, "no target in view"
            else:
                level, message = 0, f"{valid} poses of {self.taken} images"
            self._reset(now)
        return level, message, values


class PoseNode:
    """The node's work around an rclpy node: subscriptions, the worker thread, publishers."""

    def __init__(self, ros: dict[str, Any], node: Any, settings: NodeSettings) -> None:
        self.ros, self.node, self.settings = ros, node, settings
        self.log = node.get_logger()
        self.target = (
            TargetSpec.load(settings.target_file) if settings.target_file else TargetSpec.paper()
        )
        self.camera: CameraModel | None = None
        self.info_refused = ""  # why the last camera_info was refused, while no camera is set
        self.last_stamp_s: float | None = None  # the newest image stamp taken
        self.estimator: PerchingEstimator | None = None
        if settings.camera_file:
            self._use_camera(CameraModel.load(settings.camera_file))
        self.said: set[str] = set()
        # every compiled kernel before the first image: none is left to build mid-stream
        self.log.info(warm_up(self.target).describe())
        self.stats = NodeStats()
        self.gaps = StampGaps()
        self.slot = LatestImage()
        sensor, geometry, std = ros["sensor"], ros["geometry"], ros["std"]
        # camera_info: sensor-data QoS (best effort, the newest few) matches any publisher
        qos = ros["qos"].qos_profile_sensor_data
        node.create_subscription(
            sensor.CameraInfo, "camera_info", self._on_camera_info, qos, **self._overrides()
        )
        if settings.image_transport == "compressed":
            self.image_type, self.image_topic = sensor.CompressedImage, "image_raw/compressed"
        else:
            self.image_type, self.image_topic = sensor.Image, "image_raw"
        self.image_sub: Any = None
        self.match_timer: Any = None
        self._matched = False
        if not self._match_image_qos():
            # no publisher yet: best effort takes any until one is found (then matched)
            self.image_sub = node.create_subscription(
                self.image_type, self.image_topic, self._on_image, qos
            )
            self.match_timer = node.create_timer(MATCH_PERIOD_S, self._match_image_qos)
        self.pose_pub = node.create_publisher(geometry.PoseWithCovarianceStamped, "~/pose", 10)
        self.track_pub = node.create_publisher(std.String, "~/track", 10)
        self.overlay_pub = (
            node.create_publisher(sensor.CompressedImage, "~/overlay/compressed", 2)
            if settings.publish_overlay
            else None
        )
        self.tf_pub = (
            None if ros["tf"] is None else node.create_publisher(ros["tf"].TFMessage, "/tf", 10)
        )
        if ros["diagnostic"] is not None:
            self.diag_pub = node.create_publisher(
                ros["diagnostic"].DiagnosticArray, "/diagnostics", 1
            )
            node.create_timer(settings.diagnostics_period_s, self._diagnostics)
        self.worker = threading.Thread(target=self._work, name="perchpose-node", daemon=True)
        self.worker.start()

    def _overrides(self) -> dict[str, Any]:
        """``qos_overrides.<topic>.subscription.*`` parameters, where the user gives them."""
        options = self.ros["overriding"].QoSOverridingOptions.with_default_policies()
        return {"qos_overriding_options": options}

    def _match_image_qos(self) -> bool:
        """Subscribe to the images with the reliability their publishers offer, once the
        first publisher is seen; False while there is none."""
        if self._matched:
            return True
        topic = self.node.resolve_topic_name(self.image_topic)
        qos = self.ros["qos"]
        infos = self.node.get_publishers_info_by_topic(topic)
        names = [
            RELIABLE if i.qos_profile.reliability == qos.ReliabilityPolicy.RELIABLE else BEST_EFFORT
            for i in infos
        ]
        reliability = matching_reliability(names)
        if reliability is None:
            return False
        profile = qos.QoSProfile(
            depth=5,
            history=qos.HistoryPolicy.KEEP_LAST,
            reliability=(
                qos.ReliabilityPolicy.RELIABLE
                if reliability == RELIABLE
                else qos.ReliabilityPolicy.BEST_EFFORT
            ),
            durability=qos.DurabilityPolicy.VOLATILE,
        )
        if self.image_sub is not None:
            self.node.destroy_subscription(self.image_sub)
        self.image_sub = self.node.create_subscription(
            self.image_type, self.image_topic, self._on_image, profile, **self._overrides()
        )
        if self.match_timer is not None:
            self.node.destroy_timer(self.match_timer)
        self._matched = True
        taken = self.image_sub.qos_profile.reliability == qos.ReliabilityPolicy.RELIABLE
        self.log.info(
            f"{topic}: {len(names)} publisher(s), {', '.join(sorted(set(names)))}: subscribed "
            f"{RELIABLE if taken else BEST_EFFORT}"
            + ("" if (taken == (reliability == RELIABLE)) else " (as qos_overrides asks)")
        )
        return True

    # what comes in (the executor's thread)
    def _say_once(self, key: str, text: str, error: bool = True) -> None:
        # one call site per severity: rclpy refuses a site whose severity changes
        if key in self.said:
            return
        self.said.add(key)
        if error:
            self.log.error(text)
        else:
            self.log.info(text)

    def _use_camera(self, camera: CameraModel) -> None:
        warm_up(self.target, [camera])  # at once where its lens model is already built
        self.camera = camera
        self.estimator = self.settings.estimator(camera, self.target)

    def _on_camera_info(self, msg: Any) -> None:
        if self.camera is not None:
            size = (int(msg.width), int(msg.height))
            if size != self.camera.size:  # its images are counted as each is refused
                self._say_once(
                    f"info{size}",
                    f"camera_info changed size to {size[0]}x{size[1]} from the camera's "
                    f"{self.camera.width_px}x{self.camera.height_px}: its images are refused "
                    "(restart the node for a new camera)",
                )
            return
        try:
            camera = CameraModel.from_camera_info(
                camera_info_fields(msg, "camera_info"), "camera_info"
            )
        except PerchposeError as exc:
            self._say_once("info-bad", f"camera_info refused: {exc}")
            self.info_refused = str(exc)  # the diagnostics say so until a good one comes
            return
        self._use_camera(camera)
        self.log.info(f"camera from camera_info: {camera.width_px}x{camera.height_px}")

    def _on_image(self, msg: Any) -> None:
        self.stats.count("received")
        lost = self.gaps.seen(header_stamp_ns(msg.header))
        if lost:
            self.stats.count("lost", lost)
        if self.slot.put(msg, time.monotonic()):
            self.stats.count("dropped")

    # the work (its own thread)
    def _work(self) -> None:
        """Take the newest image until closed; no frame's trouble ends the thread."""
        while not self.slot.closed:
            item = self.slot.take(0.5)
            if item is None:
                continue
            try:
                self._process(*item)
            except PerchposeError as exc:
                self.stats.count("refused")
                self._say_once(str(exc), str(exc))
            except Exception as exc:  # a publisher that went away at shutdown, say
                if self.slot.closed:
                    return
                try:
                    self._say_once(type(exc).__name__, f"frame failed: {exc!r}")
                except Exception:  # the log itself failing: the next frame goes on regardless
                    self.stats.count("refused")

    def _process(self, msg: Any, received_s: float) -> None:
        camera, estimator = self.camera, self.estimator
        if camera is None or estimator is None:  # /diagnostics says so while it lasts
            self._say_once("no-camera", "waiting for camera_info (or set camera_file)", False)
            return
        frame_id = str(msg.header.frame_id)
        stamp = Stamp.of_message(header_stamp_ns(msg.header), frame_id, self.settings.camera_frame)
        try:
            image = image_of(msg, "image_raw")
            grey = camera.check_image(image, "image_raw")
        except (SourceError, PerchposeError) as exc:
            self.stats.count("refused")
            self._say_once(f"image {exc}", f"{exc}; refused")
            return
        if not self._in_order(stamp.t_s, estimator):
            return
        estimate = estimator.update(grey, stamp.t_s)
        latency_s = time.monotonic() - received_s
        estimate = replace(estimate, latency_s=latency_s, grabbed_s=received_s)
        self._publish(stamp, estimate, image)
        self.stats.took(estimate, latency_s)

    def _in_order(self, t_s: float, estimator: PerchingEstimator) -> bool:
        """A stamp a little behind the last one is a frame out of order: refused. One at least
        ``RESTART_BACK_S`` behind is a camera whose clock started over (its driver restarted,
        a bag played again): said once per restart, and tracking starts over from it."""
        last = self.last_stamp_s
        if last is not None and t_s < last:
            back_s = last - t_s
            if back_s < RESTART_BACK_S:
                self.stats.count("refused")
                self._say_once(
                    "stamp-back",
                    f"image_raw: a stamp {1000 * back_s:.1f} ms behind the one before; refused "
                    "(out of order)",
                )
                return False
            self.log.warning(
                f"image_raw: the stamps went back {back_s:.1f} s (a camera driver that "
                "restarted, or a bag played again): tracking starts over from this frame"
            )
            estimator.reset()
        self.last_stamp_s = t_s
        return True

    def _header(self, stamp: Stamp) -> Any:
        std = self.ros["std"]
        sec, nanosec = stamp.sec_nanosec
        time = self.ros["builtin"].Time(sec=sec, nanosec=nanosec)
        return std.Header(stamp=time, frame_id=stamp.frame_id)

    def _publish(self, stamp: Stamp, estimate: Estimate, image: Any) -> None:
        geometry, std = self.ros["geometry"], self.ros["std"]
        header = self._header(stamp)
        if estimate.valid:
            fields_ = pose_fields(estimate)
            x, y, z = fields_.position
            qx, qy, qz, qw = fields_.orientation
            msg = geometry.PoseWithCovarianceStamped(header=header)
            msg.pose.pose.position = geometry.Point(x=x, y=y, z=z)
            msg.pose.pose.orientation = geometry.Quaternion(x=qx, y=qy, z=qz, w=qw)
            msg.pose.covariance = fields_.covariance.tolist()
            self.pose_pub.publish(msg)
            if self.tf_pub is not None:
                transform = geometry.TransformStamped(header=header)
                transform.child_frame_id = self.settings.target_frame
                transform.transform.translation = geometry.Vector3(x=x, y=y, z=z)
                transform.transform.rotation = msg.pose.pose.orientation
                self.tf_pub.publish(self.ros["tf"].TFMessage(transforms=[transform]))
        row = estimate_row(self.stats.total_taken, stamp.t_s, estimate, self.target, "", "")
        text = track_json(row) | {"stamp_ns": stamp.t_ns, "frame_id": stamp.frame_id}
        self.track_pub.publish(std.String(data=json.dumps(text)))
        if self.overlay_pub is not None and self.camera is not None:
            picture = draw_overlay(image, estimate, self.camera, note=f"t {stamp.t_s:.2f} s")
            jpeg = encode_jpeg(picture, 80)
            if jpeg is not None:
                compressed = self.ros["sensor"].CompressedImage(header=header, format="jpeg")
                compressed.data = bytes(jpeg)
                self.overlay_pub.publish(compressed)

    def waiting_for(self) -> str:
        """What the node waits for before it can track (empty: nothing), as the diagnostics
        say it: a camera_info, and why the last one was refused."""
        if self.camera is not None:
            return ""
        refused = f" (the last refused: {self.info_refused})" if self.info_refused else ""
        return f"camera_info{refused}"

    def _diagnostics(self) -> None:
        diagnostic = self.ros["diagnostic"]
        level, message, values = self.stats.report(self.waiting_for())
        status = diagnostic.DiagnosticStatus(
            level=bytes([level]),
            name="perchpose: target pose",
            message=message,
            hardware_id=self.settings.camera_frame or CAMERA_FRAME,
            values=[diagnostic.KeyValue(key=k, value=v) for k, v in values.items()],
        )
        array = diagnostic.DiagnosticArray(status=[status])
        array.header.stamp = self.node.get_clock().now().to_msg()
        self.diag_pub.publish(array)

    def close(self) -> None:
        self.slot.close()
        self.worker.join(timeout=5.0)


def _typed(name: str, value: Any, default: Any) -> Any:
    """A parameter's value as its default's type (an integer where a number is due)."""
    if isinstance(default, bool):
        if not isinstance(value, bool):
            raise PerchposeError(f"parameter {name}: true or false, got {value!r}")
        return value
    if isinstance(default, float):
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise PerchposeError(f"parameter {name}: a number, got {value!r}")
        return float(value)
    if not isinstance(value, str):
        raise PerchposeError(f"parameter {name}: a string, got {value!r}")
    return value


def _settings(node: Any) -> NodeSettings:
    """The parameters, declared with the shipped file's defaults and read back."""
    descriptor = importlib.import_module("rcl_interfaces.msg").ParameterDescriptor
    values = {}
    for name, default in NodeSettings.defaults().items():
        node.declare_parameter(name, default, descriptor(dynamic_typing=True))
        values[name] = _typed(name, node.get_parameter(name).value, default)
    return NodeSettings(**values)


def run(args: list[str]) -> None:
    """Run the node until interrupted; ``args`` are ROS's (``--ros-args ...``)."""
    ros = _ros()
    rclpy = ros["rclpy"]
    rclpy.init(args=[NODE_NAME, *args])
    node = rclpy.create_node(NODE_NAME)
    work = None
    try:
        work = PoseNode(ros, node, _settings(node))
        log = node.get_logger()
        if ros["tf"] is None:
            log.info("tf2_msgs is not importable: no /tf (the pose names its frame all the same)")
        image, pose = node.resolve_topic_name("image_raw"), node.resolve_topic_name("~/pose")
        log.info(f"tracking {image} -> {pose}")
        executor = ros["executors"].SingleThreadedExecutor()
        executor.add_node(node)
        try:
            executor.spin()
        except (KeyboardInterrupt, ros["executors"].ExternalShutdownException):
            pass
    finally:
        if work is not None:
            work.close()
        node.destroy_node()
        if rclpy.ok():
            rclpy.shutdown()

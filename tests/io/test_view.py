"""The live view over a real WebSocket: its server (``perchpose.io.view_server``), and a client
(``websockets``) that speaks the Foxglove WebSocket protocol to it: it reads the advertised
channels, subscribes, and decodes what it receives. What it advertises and sends is checked
against foxglove-sdk's own server for the same messages."""

import json
import struct
import subprocess
import sys
import time
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest

pytest.importorskip("foxglove")
pytest.importorskip("websockets")

from websockets.sync.client import connect

from perchpose import CameraModel, PerchingEstimator, TargetSpec
from perchpose.geometry import facing_pose
from perchpose.io.frames import Stamp, stamp_ns
from perchpose.io.overlay import draw_overlay
from perchpose.io.view import LiveView
from perchpose.sim.render import Renderer

SUBPROTOCOL = "foxglove.sdk.v1"  # what foxglove-sdk servers speak (the ws-protocol v1 framing)
MESSAGE_DATA = 1


def _listening_ports() -> set[int]:
    """The TCP ports this process listens on (Linux's /proc)."""
    import os

    inodes = {
        os.readlink(f"/proc/self/fd/{fd}")[8:-1]
        for fd in os.listdir("/proc/self/fd")
        if os.path.exists(f"/proc/self/fd/{fd}")
        and os.readlink(f"/proc/self/fd/{fd}").startswith("socket:[")
    }
    ports = set()
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        with open(table) as rows:
            for row in list(rows)[1:]:
                fields = row.split()
                if fields[3] == "0A" and fields[9] in inodes:  # LISTEN
                    ports.add(int(fields[1].rsplit(":", 1)[1], 16))
    return ports


def _until(condition: Callable[[], bool], timeout_s: float = 5.0) -> bool:
    """Wait for ``condition`` (the server's own thread changes it); whether it came."""
    deadline = time.monotonic() + timeout_s
    while not condition() and time.monotonic() < deadline:
        time.sleep(0.01)
    return condition()


def _json_until(ws: Any, op: str) -> dict[str, Any]:
    while True:
        frame = ws.recv(timeout=5)
        if isinstance(frame, str):
            message = json.loads(frame)
            if message.get("op") == op:
                return message


def test_a_client_subscribes_and_decodes_the_frames() -> None:
    camera = CameraModel.preset("webcam")
    target = TargetSpec.paper()
    renderer = Renderer(camera, target)
    T = facing_pose(0.02, -0.01, 0.5, 0.7)
    image = renderer.render(T, rng=np.random.default_rng(0))
    estimate = PerchingEstimator(camera, target).update(image, 0.0)
    assert estimate.valid
    overlay = draw_overlay(image, estimate, camera)
    view = LiveView(target, port=0)
    try:
        with connect(f"ws://127.0.0.1:{view.port}", subprotocols=[SUBPROTOCOL]) as ws:
            _json_until(ws, "serverInfo")
            channels: dict[str, dict[str, Any]] = {}
            while len(channels) < 5:
                for channel in _json_until(ws, "advertise")["channels"]:
                    channels[channel["topic"]] = channel
            assert channels["/perchpose/pose"]["schemaName"] == "foxglove.PoseInFrame"
            assert channels["/tf"]["schemaName"] == "foxglove.FrameTransforms"
            assert channels["/perchpose/estimate"]["encoding"] == "json"
            topics = ("/perchpose/estimate", "/perchpose/overlay", "/perchpose/pose")
            subscriptions = {k: channels[t]["id"] for k, t in enumerate(topics)}
            ws.send(
                json.dumps(
                    {
                        "op": "subscribe",
                        "subscriptions": [
                            {"id": k, "channelId": c} for k, c in subscriptions.items()
                        ],
                    }
                )
            )
            received: dict[int, list[bytes]] = {}
            for k in range(20):
                view.publish(Stamp(k / 30, stamp_ns(k / 30)), estimate, overlay)
                try:
                    while True:
                        frame = ws.recv(timeout=0.05)
                        if isinstance(frame, bytes) and frame[0] == MESSAGE_DATA:
                            (sub,) = struct.unpack_from("<I", frame, 1)
                            received.setdefault(sub, []).append(frame[13:])
                except TimeoutError:
                    pass
                if len(received) == 3:
                    break
    finally:
        view.close()
    assert set(received) == {0, 1, 2}
    decoded = json.loads(received[0][-1])
    assert decoded["valid"] is True
    assert decoded["stage"] == estimate.stage
    assert decoded["z_cm"] == pytest.approx(estimate.z_cm)
    assert decoded["yaw_deg"] == pytest.approx(estimate.yaw_deg)
    assert decoded["predicted"] is False
    assert decoded["age_s"] == 0.0
    assert decoded["measured"] == estimate.measured_label
    assert b"\xff\xd8\xff" in received[1][-1]  # the overlay's JPEG inside its message
    # the pose message carries the position as doubles
    assert struct.pack("<d", estimate.t_camera_target_m[2]) in received[2][-1]


def test_without_view_nothing_of_it_is_imported() -> None:
    code = (
        "import sys, perchpose.cli, perchpose.app.track; "
        "print(any(m.startswith(('foxglove', 'websockets')) for m in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


def test_track_serves_the_view_while_it_runs(
    approach_webcam_dir: Any,
    tmp_path: Any,
    capsys: pytest.CaptureFixture[str],
    track_argv: Callable[..., list[str]],
) -> None:
    from perchpose.cli import main

    code = main(
        track_argv(approach_webcam_dir, tmp_path / "p.csv", "--quiet", "--view", "--view-port", "0")
    )
    assert code == 0
    assert "live view for Foxglove at ws://127.0.0.1:" in capsys.readouterr().err


def test_a_web_page_of_another_origin_is_refused_and_said_once() -> None:
    """A browser sends its page's Origin: a page from anywhere else could read the overlay
    and the pose, so only no Origin (native apps, scripts), the Foxglove web app's and those
    the user allows are relayed; others get HTTP 403, and a client that does not speak
    foxglove.sdk.v1 HTTP 400, each said once with the reason."""
    from websockets.exceptions import InvalidStatus

    reports: list[str] = []
    view = LiveView(
        TargetSpec.paper(),
        port=0,
        allowed_origins=("http://localhost:8080",),
        report=reports.append,
    )
    url = f"ws://127.0.0.1:{view.port}"
    try:
        for _ in range(2):
            with pytest.raises(InvalidStatus) as refused:
                connect(url, subprotocols=[SUBPROTOCOL], origin="http://evil.example")
            assert refused.value.response.status_code == 403
        with pytest.raises(InvalidStatus) as old:
            connect(url, subprotocols=["foxglove.websocket.v1"])
        assert old.value.response.status_code == 400
        for origin in ("https://app.foxglove.dev", "http://localhost:8080"):
            with connect(url, subprotocols=[SUBPROTOCOL], origin=origin) as ws:
                assert _json_until(ws, "serverInfo")["name"] == "perchpose"
    finally:
        view.close()
    assert view.server.refused == 3
    assert len(reports) == 2
    assert "Origin http://evil.example is not allowed (--view-origin" in reports[0]
    assert "offers foxglove.websocket.v1, not foxglove.sdk.v1" in reports[1]


def _subscribe_all(ws: Any) -> dict[str, int]:
    """Read serverInfo and the advertisements, subscribe to every channel (subscription id =
    channel id); the topics' subscription ids."""
    _json_until(ws, "serverInfo")
    channels = _json_until(ws, "advertise")["channels"]
    ws.send(
        json.dumps(
            {
                "op": "subscribe",
                "subscriptions": [{"id": c["id"], "channelId": c["id"]} for c in channels],
            }
        )
    )
    return {c["topic"]: c["id"] for c in channels}


def test_the_view_listens_on_one_port_only() -> None:
    before = _listening_ports()
    view = LiveView(TargetSpec.paper(), port=0)
    try:
        assert _listening_ports() - before == {view.port}
    finally:
        view.close()
    assert view.port not in _listening_ports()


def _decoder(advertised: dict[str, Any]) -> Any:
    """The message class an independent protobuf reader builds from an advertised schema (a
    FileDescriptorSet), as Foxglove decodes a channel."""
    import base64

    from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

    files = descriptor_pb2.FileDescriptorSet.FromString(base64.b64decode(advertised["schema"]))
    pool = descriptor_pool.DescriptorPool()
    for file in files.file:
        pool.Add(file)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(advertised["schemaName"]))


def _foxglove_sdk_advertises() -> dict[str, dict[str, Any]]:
    """What foxglove-sdk's own server advertises for the view's protobuf channels."""
    import foxglove
    import foxglove.channels as typed

    sdk = foxglove.start_server(name="reference", host="127.0.0.1", port=0)
    kept = [  # the channels live as long as they are referenced
        typed.CompressedImageChannel("/perchpose/overlay"),
        typed.PoseInFrameChannel("/perchpose/pose"),
        typed.FrameTransformsChannel("/tf"),
        typed.SceneUpdateChannel("/perchpose/scene"),
    ]
    try:
        with connect(f"ws://127.0.0.1:{sdk.port}", subprotocols=[SUBPROTOCOL]) as ws:
            _json_until(ws, "serverInfo")
            advertised = _json_until(ws, "advertise")["channels"]
    finally:
        sdk.stop()
    assert len(kept) == len(advertised)
    return {c["topic"]: c for c in advertised}


def test_it_advertises_as_foxglove_sdks_server_and_its_messages_decode() -> None:
    """foxglove-sdk's own server advertises the same topics with the same schemas, byte for
    byte; every message served decodes with the schema advertised for it (google.protobuf)."""
    pytest.importorskip("google.protobuf")
    camera = CameraModel.preset("webcam")
    target = TargetSpec.paper()
    image = Renderer(camera, target).render(
        facing_pose(0.0, 0.01, 0.6, 0.2), rng=np.random.default_rng(1)
    )
    estimate = PerchingEstimator(camera, target).update(image, 0.0)
    assert estimate.valid
    overlay = draw_overlay(image, estimate, camera)
    theirs = _foxglove_sdk_advertises()
    assert len(theirs) == 4
    view = LiveView(target, port=0)
    received: dict[int, bytes] = {}
    try:
        with connect(f"ws://127.0.0.1:{view.port}", subprotocols=[SUBPROTOCOL]) as ws:
            _json_until(ws, "serverInfo")
            ours = {c["topic"]: c for c in _json_until(ws, "advertise")["channels"]}
            ws.send(
                json.dumps(
                    {
                        "op": "subscribe",
                        "subscriptions": [
                            {"id": 10 + c["id"], "channelId": c["id"]} for c in ours.values()
                        ],
                    }
                )
            )
            _until(lambda: view.wants_overlay)
            view.publish(Stamp(1.5, stamp_ns(1.5)), estimate, overlay)
            while len(received) < 5:
                frame = ws.recv(timeout=5)
                assert isinstance(frame, bytes)
                assert frame[0] == MESSAGE_DATA
                sub, t_ns = struct.unpack_from("<IQ", frame, 1)
                assert t_ns == stamp_ns(1.5)
                received[sub - 10] = frame[13:]
    finally:
        view.close()
    for topic, advertised in theirs.items():
        for key in ("encoding", "schemaName", "schemaEncoding", "schema"):
            assert ours[topic][key] == advertised[key], (topic, key)
    decoded = {
        topic: _decoder(ours[topic]).FromString(received[ours[topic]["id"]]) for topic in theirs
    }
    assert decoded["/perchpose/pose"].pose.position.z == pytest.approx(estimate.z_cm / 100)
    assert decoded["/perchpose/overlay"].format == "jpeg"
    assert decoded["/perchpose/overlay"].data[:3] == b"\xff\xd8\xff"
    assert decoded["/perchpose/overlay"].timestamp.seconds == 1
    assert decoded["/perchpose/overlay"].timestamp.nanos == 500_000_000
    transform = decoded["/tf"].transforms[0]
    assert transform.child_frame_id == "target"
    assert transform.translation.x == pytest.approx(estimate.t_camera_target_m[0])
    assert decoded["/perchpose/scene"].entities[0].frame_id == "target"
    assert json.loads(received[ours["/perchpose/estimate"]["id"]])["valid"] is True
    assert ours["/perchpose/estimate"]["schemaEncoding"] == "jsonschema"


def test_messages_go_only_where_subscribed_and_bad_requests_get_a_status() -> None:
    view = LiveView(TargetSpec.paper(), port=0)
    try:
        with connect(f"ws://127.0.0.1:{view.port}", subprotocols=[SUBPROTOCOL]) as ws:
            ids = _subscribe_all(ws)
            ws.send(json.dumps({"op": "unsubscribe", "subscriptionIds": [ids["/perchpose/pose"]]}))
            ws.send(json.dumps({"op": "subscribe", "subscriptions": [{"id": 99, "channelId": 42}]}))
            assert "no channel 42" in _json_until(ws, "status")["message"]
            ws.send(json.dumps({"op": "getParameters", "parameterNames": []}))
            status = _json_until(ws, "status")
            assert status["level"] == 2
            assert "'getParameters' is not served" in status["message"]
            assert not view.server.subscribed(2)  # the pose: unsubscribed
            view.publish(Stamp(0.0, 0), None, None)  # no estimate: the estimate channel only
            frame = ws.recv(timeout=5)
            assert isinstance(frame, bytes)
            (sub,) = struct.unpack_from("<I", frame, 1)
            assert sub == ids["/perchpose/estimate"]
            assert json.loads(frame[13:]) == {"t_s": 0.0, "valid": False}
        assert _until(lambda: not view.wants_overlay)  # the client gone, so its subscriptions
    finally:
        view.close()

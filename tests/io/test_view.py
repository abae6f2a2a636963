"""The live view over a real WebSocket: a Foxglove server from foxglove-sdk, and a client
(``websockets``) that speaks the Foxglove WebSocket protocol to it: it reads the advertised
channels, subscribes, and decodes what it receives."""

import json
import struct
import subprocess
import sys
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
    assert view.gate.refused == 3
    assert len(reports) == 2
    assert "Origin http://evil.example is not allowed (--view-origin" in reports[0]
    assert "offers foxglove.websocket.v1, not foxglove.sdk.v1" in reports[1]

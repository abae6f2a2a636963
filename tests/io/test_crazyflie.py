"""PerchingPilot against cflib's own Crazyflie and Commander over a fake radio link.

The fake link stands in for the radio only: it records the CRTP packets cflib builds and answers
the firmware's protocol-version handshake, so cflib picks today's setpoint encodings.
"""

import math
import queue
import struct
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from cflib.crazyflie import Crazyflie
from cflib.crtp.crtpstack import CRTPPacket, CRTPPort

from perchpose import CameraModel, PerchingEstimator, TargetSpec
from perchpose.cli import main
from perchpose.control import PerchingController, PerchingPilot, PilotSettings
from perchpose.control.gyro import GyroAttitude
from perchpose.control.lean import CRAZYFLIE_KALMAN_LAG_S
from perchpose.control.pilot import SenseAges
from perchpose.errors import ControllerConfigError, LinkError
from perchpose.geometry import roll_pitch_rad, yaw_rad
from perchpose.io.crazyflie import CflibCommander, connect
from perchpose.io.samples import SampleGate
from perchpose.values import Estimate

PROTOCOL_VERSION = 10
VELOCITIES = PilotSettings(command="velocity")  # the tests that read velocity packets


class FakeRadioLink:
    """The lowest layer cflib talks to: a queue of incoming packets and a list of sent ones."""

    needs_resending = False

    def __init__(self) -> None:
        self.sent: list[tuple[int, int, bytes]] = []
        self.incoming: queue.Queue[CRTPPacket] = queue.Queue()

    def send_packet(self, pk: CRTPPacket) -> None:
        self.sent.append((pk.port, pk.channel, bytes(pk.data)))
        if pk.port == CRTPPort.LINKCTRL and pk.channel == 1:  # link service "source" request
            self._reply(CRTPPort.LINKCTRL, 1, b"Bitcraze Crazyflie\x00")
        elif pk.port == CRTPPort.PLATFORM and pk.channel == 1 and pk.data[0] == 0:
            self._reply(CRTPPort.PLATFORM, 1, bytes([0, PROTOCOL_VERSION]))

    def _reply(self, port: int, channel: int, data: bytes) -> None:
        pk = CRTPPacket()
        pk.set_header(port, channel)
        pk.data = data
        self.incoming.put(pk)

    def receive_packet(self, wait: float = 0) -> CRTPPacket | None:
        try:
            return self.incoming.get(timeout=max(wait, 0.001))
        except queue.Empty:
            return None

    def close(self) -> None:
        pass


def decode(packet: tuple[int, int, bytes]) -> tuple[Any, ...]:
    """A commander packet as (kind, values...)."""
    port, channel, data = packet
    if port == CRTPPort.COMMANDER:  # the legacy setpoint: roll, pitch, yaw rate, thrust
        roll, pitch, yaw_rate, thrust = struct.unpack("<fffH", data)
        return ("rpyt", roll, pitch, yaw_rate, thrust)
    assert port == CRTPPort.COMMANDER_GENERIC
    if channel == 1:
        kind, remain_ms = struct.unpack("<BI", data)
        assert kind == 0
        return ("notify_stop", remain_ms)
    if data[0] == 0:
        return ("stop",)
    kind, vx, vy, vz, yaw_rate = struct.unpack("<Bffff", data)
    assert kind == 8  # TYPE_VELOCITY_WORLD
    return ("velocity", vx, vy, vz, yaw_rate)


@pytest.fixture
def crazyflie() -> tuple[Crazyflie, FakeRadioLink]:
    link = FakeRadioLink()
    cf = Crazyflie(link=link)
    done: queue.Queue[bool] = queue.Queue()
    cf.platform.fetch_platform_informations(lambda: done.put(True))
    assert done.get(timeout=5.0)
    assert cf.platform.get_protocol_version() == PROTOCOL_VERSION
    link.sent.clear()
    yield cf, link
    cf.incoming.stop()


@pytest.fixture(scope="module")
def estimates(approach_fpv_dir: Path) -> list[Estimate]:
    """Five blank frames, then the rendered approach (with its 0.4 s dropout), 30 fps."""
    camera = CameraModel.load(approach_fpv_dir / "camera.yaml")
    estimator = PerchingEstimator(camera, TargetSpec.paper())
    frames = sorted(approach_fpv_dir.glob("frame_*.png"))
    blank = np.full((camera.height_px, camera.width_px), 128, np.uint8)
    images = [blank] * 5 + [cv2.imread(str(p), cv2.IMREAD_GRAYSCALE) for p in frames]
    return [estimator.update(image, i / 30.0) for i, image in enumerate(images)]


def level() -> np.ndarray:
    return np.eye(3)


def fly(
    cf: Crazyflie,
    estimates: list[Estimate],
    settings: PilotSettings | None = None,
    height_m: Callable[[], float] | None = None,
) -> tuple[PerchingPilot, list[Any]]:
    pilot = PerchingPilot(
        CflibCommander(cf.commander),
        level,
        settings=settings,
        height_m=height_m,
        report=lambda _m: None,
    )
    pilot.watch_link(cf)
    steps = [pilot.update(e, e.t_s) for e in estimates]
    return pilot, steps


def test_setpoints_are_the_controllers(
    crazyflie: tuple[Crazyflie, FakeRadioLink], estimates: list[Estimate]
) -> None:
    cf, link = crazyflie
    pilot, steps = fly(cf, estimates)
    packets = [decode(p) for p in link.sent]
    assert all(p[0] == "velocity" for p in packets)
    # nothing before the first valid estimate, then one setpoint per frame
    first = next(i for i, e in enumerate(estimates) if e.valid)
    assert first >= 5
    assert all(s.v_mps is None for s in steps[:first])
    assert len(packets) == len(estimates) - first
    reference = PerchingController()
    for estimate, packet in zip(estimates[first:], packets, strict=True):
        command = reference.update(estimate, estimate.t_s, np.eye(3))
        assert packet[1:4] == pytest.approx(command.v_mps, abs=1e-6)
        assert packet[4] == pytest.approx(math.degrees(command.yaw_rate_rad_s), abs=1e-4)
    # the target climbs into view: the vehicle rises towards it
    assert max(p[3] for p in packets) > 0.05
    # the dropout: held in place while the target is lost, then back to perching
    lost = [s for s in steps if s.state == "lost"]
    assert lost
    assert all(s.v_mps == (0.0, 0.0, 0.0) for s in lost)
    assert steps[-1].state == "perching"
    assert [t[1:] for t in pilot.transitions] == [
        ("waiting", "perching"),
        ("perching", "lost"),
        ("lost", "perching"),
    ]


def test_a_long_loss_lands_and_then_stays_silent(
    crazyflie: tuple[Crazyflie, FakeRadioLink], estimates: list[Estimate]
) -> None:
    cf, link = crazyflie
    settings = PilotSettings(land_after_lost_s=0.1)
    height = [0.32]
    pilot = PerchingPilot(
        CflibCommander(cf.commander),
        level,
        settings=settings,
        height_m=lambda: height[0],
        report=lambda _m: None,
    )
    pilot.watch_link(cf)
    steps = []
    for estimate in estimates:
        steps.append(pilot.update(estimate, estimate.t_s))
        if pilot.state == "landing":  # 2 cm a landing frame down to the floor, 1 cm up
            height[0] = max(0.01, height[0] - 0.02)
    packets = [decode(p) for p in link.sent]
    states = [t[2] for t in pilot.transitions]
    assert states == ["perching", "lost", "landing", "landed"]
    landing = [s for s in steps if s.state == "landing"]
    assert landing
    assert all(s.v_mps == (0.0, 0.0, -settings.land_speed_mps) for s in landing)
    # on the floor from the 15th landing frame: touchdown once it has been still for the window
    assert 15 + 14 <= len(landing) <= 15 + 16
    # a stop setpoint and the priority release end the flight; the target's return is ignored
    assert packets[-2:] == [("stop",), ("notify_stop", 0)]
    landed_at = next(i for i, s in enumerate(steps) if s.state == "landed")
    assert any(e.valid for e in estimates[landed_at + 1 :])
    assert all(s.v_mps is None for s in steps[landed_at + 1 :])


def test_link_loss_stops_all_setpoints(
    crazyflie: tuple[Crazyflie, FakeRadioLink], estimates: list[Estimate]
) -> None:
    cf, link = crazyflie
    pilot = PerchingPilot(CflibCommander(cf.commander), level, report=lambda _m: None)
    pilot.watch_link(cf)
    half = len(estimates) // 2
    for e in estimates[:half]:
        pilot.update(e, e.t_s)
    sent_before = len(link.sent)
    assert sent_before > 0
    cf.connection_lost.call("radio://0/80/2M/E7E7E7E7E7", "Too many packets lost")
    assert pilot.state == "link_lost"
    for e in estimates[half:]:
        pilot.update(e, e.t_s)
    assert len(link.sent) == sent_before


def test_abort_lands_in_real_time(
    crazyflie: tuple[Crazyflie, FakeRadioLink], estimates: list[Estimate]
) -> None:
    """After Ctrl-C the landing runs on the pilot's clock, a setpoint every period, until the
    height has rested on the floor for the touchdown window: then the stop."""
    cf, link = crazyflie
    now = [100.0]

    def height_m() -> float:  # the vehicle comes down at the landing speed to the floor
        return max(0.0, 0.5 - 0.2 * (now[0] - 100.0))

    pilot = PerchingPilot(
        CflibCommander(cf.commander), level, height_m=height_m, report=lambda _m: None
    )
    for e in estimates[:30]:
        pilot.update(e, e.t_s)
    link.sent.clear()

    def sleep(dt: float) -> None:
        now[0] += dt

    pilot.abort(estimates[29].t_s, "Ctrl-C")
    pilot.land(clock=lambda: now[0], sleep=sleep)
    packets = [decode(p) for p in link.sent]
    assert packets[-2:] == [("stop",), ("notify_stop", 0)]
    descent = packets[:-2]
    assert descent == [("velocity", 0.0, 0.0, pytest.approx(-0.2), 0.0)] * len(descent)
    # on the floor 2.5 s in; the last 2 cm already read as still: 2.4 s + the 0.5 s window
    period = pilot.settings.setpoint_period_s
    assert (2.4 + 0.5) / period - 1 <= len(descent) <= (2.5 + 0.5) / period + 1
    assert pilot.state == "landed"


def _near_then_blind(pilot: PerchingPilot) -> None:
    """Three frames with the magnet 3 cm under the target centre, then 1.5 s in which the
    camera, too close, sees nothing."""
    near = Estimate.of_pose(0.0, (-0.015, 0.0, 0.01), 0.0, stage=3)
    for i in range(3):
        pilot.update(replace(near, t_s=i / 30.0), i / 30.0)
    for i in range(3, 48):
        pilot.update(None, i / 30.0)


def test_commit_ends_perched_only_on_contact(crazyflie: tuple[Crazyflie, FakeRadioLink]) -> None:
    """The final climb runs until the vehicle's height stops rising against the plate."""
    cf, link = crazyflie
    height = [1.90]

    def height_m() -> float:  # climbs at the commit speed, stalls at the plate (1.95 m)
        height[0] = min(1.95, height[0] + 0.15 / 30.0)
        return height[0]

    pilot = PerchingPilot(
        CflibCommander(cf.commander), level, height_m=height_m, report=lambda _m: None
    )
    _near_then_blind(pilot)
    packets = [decode(p) for p in link.sent]
    climbs = [p for p in packets if p[0] == "velocity"]
    assert all(p[3] == pytest.approx(pilot.controller.settings.commit_speed_mps) for p in climbs)
    # then the magnet's hold tried: the legacy setpoint's thrust unlocked (one with none),
    # a quarter of the PID's hover thrust, level, and the stop once the height held
    check = packets[len(climbs) : -2]
    assert check[0] == ("rpyt", 0.0, 0.0, 0.0, 0)
    assert set(check[1:]) == {("rpyt", 0.0, 0.0, 0.0, 9000)}
    period = pilot.settings.setpoint_period_s
    assert len(check) >= pilot.settings.seat_check_s / period
    assert packets[-2:] == [("stop",), ("notify_stop", 0)]
    assert pilot.state == "perched"
    # stopped 0.3 s (the contact window) after the climb stalled, not on a timer
    stalled_at = math.ceil((1.95 - 1.90) / (0.15 / 30.0))  # samples until the plate
    assert len(climbs) >= stalled_at


def test_time_alone_never_stops_the_motors(crazyflie: tuple[Crazyflie, FakeRadioLink]) -> None:
    """Without contact evidence (no height source, or a height that keeps rising) a final
    climb that does not end backs off instead of stopping the motors."""
    cf, link = crazyflie
    for height_m in (None, iter(np.arange(0.0, 5.0, 0.01)).__next__):
        link.sent.clear()
        pilot = PerchingPilot(
            CflibCommander(cf.commander), level, height_m=height_m, report=lambda _m: None
        )
        near = Estimate.of_pose(0.0, (-0.015, 0.0, 0.01), 0.0, stage=3)
        for i in range(3):
            pilot.update(replace(near, t_s=i / 30.0), i / 30.0)
        phases = [pilot.update(None, i / 30.0).phase for i in range(3, 100)]
        packets = [decode(p) for p in link.sent]
        assert all(p[0] == "velocity" for p in packets)
        assert pilot.state == "lost"
        assert "commit" in phases
        assert phases[-1] == "lost"


def test_one_outlier_frame_neither_commits_nor_stops(
    crazyflie: tuple[Crazyflie, FakeRadioLink],
) -> None:
    """30 frames with the target 60 cm above, one frame at (-1.5, 0, 3) cm, then 60 frames at
    60 cm again: the pilot keeps flying on the later frames and never stops the motors."""
    cf, link = crazyflie
    pilot = PerchingPilot(
        CflibCommander(cf.commander), level, height_m=lambda: 1.0, report=lambda _m: None
    )
    far = (0.0, 0.0, 0.60)
    frames = [far] * 30 + [(-0.015, 0.0, 0.03)] + [far] * 60
    steps = [
        pilot.update(Estimate.of_pose(k / 30.0, p, 0.0), k / 30.0) for k, p in enumerate(frames)
    ]
    packets = [decode(p) for p in link.sent]
    assert all(p[0] == "velocity" for p in packets)
    assert len(packets) == len(frames)
    assert pilot.state == "perching"
    assert "commit" not in {s.phase for s in steps}
    assert steps[-1].v_mps is not None
    assert steps[-1].v_mps[2] > 0.1  # climbing towards the target 60 cm above


def test_stale_or_non_finite_estimates_are_not_flown(
    crazyflie: tuple[Crazyflie, FakeRadioLink],
) -> None:
    cf, link = crazyflie
    pilot = PerchingPilot(
        CflibCommander(cf.commander), level, height_m=lambda: 1.0, report=lambda _m: None
    )
    old = Estimate.of_pose(0.0, (0.1, 0.0, 0.6), 0.0, age_s=5.0)
    assert pilot.update(old, 0.0).v_mps is None  # never takes over on a stale pose
    assert pilot.update(Estimate.of_pose(0.0, (0.1, 0.0, 0.6), 0.0), 0.0).v_mps is not None
    late = pilot.update(Estimate.of_pose(0.1, (0.1, 0.0, 0.6), 0.0), 2.0)  # captured 1.9 s ago
    assert late.phase == "lost"
    assert late.v_mps == (0.0, 0.0, 0.0)
    nan = Estimate.of_pose(2.1, (math.nan, 0.0, 0.6), 0.0)
    assert pilot.update(nan, 2.1).phase == "lost"
    # a non-finite attitude from the vehicle is never flown on: a hover goes out, and a
    # second of them lands the vehicle
    pilot.attitude = lambda: np.full((3, 3), np.nan)
    step = pilot.update(Estimate.of_pose(2.2, (0.1, 0.0, 0.6), 0.0), 2.2)
    assert (step.phase, step.v_mps) == ("hold", (0.0, 0.0, 0.0))
    assert pilot.update(Estimate.of_pose(2.9, (0.1, 0.0, 0.6), 0.0), 2.9).phase == "hold"
    assert pilot.update(Estimate.of_pose(3.0, (0.1, 0.0, 0.6), 0.0), 3.0).state == "landing"
    assert pilot.replaced_setpoints == 0
    velocities = [decode(p)[1:] for p in link.sent]
    assert all(math.isfinite(v) for packet in velocities for v in packet)


def test_bad_uri_and_settings() -> None:
    with pytest.raises(LinkError, match="radio://"):
        connect("http://example.com")
    with pytest.raises(ControllerConfigError, match="land_speed_mps"):
        PilotSettings(land_speed_mps=0.0)
    with pytest.raises(ControllerConfigError, match="must be below senses_lost_after_s"):
        PilotSettings(stale_after_s=2.0)
    with pytest.raises(ControllerConfigError, match="on_senses_lost 'hover'"):
        PilotSettings(on_senses_lost="hover")
    with pytest.raises(ControllerConfigError, match="a frozen height would read as contact"):
        PilotSettings(live_height_s=0.4)


def test_cli_without_a_radio_is_one_line(
    approach_fpv_dir: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    track_argv: Callable[..., list[str]],
) -> None:
    uri = "radio://0/80/2M/E7E7E7E7E7"
    code = main(
        track_argv(
            approach_fpv_dir,
            tmp_path / "p.csv",
            "--crazyflie",
            uri,
            "--realtime",
            camera="preset:fpv",
        )
    )
    assert code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1
    assert uri in err[0]


def test_nothing_imports_cflib_without_the_crazyflie_link() -> None:
    import subprocess
    import sys

    code = (
        "import sys, perchpose.cli, perchpose.app.track, perchpose.io.crazyflie, "
        "perchpose.io.mavlink.landing_target_sink; print('cflib' in sys.modules)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


def bare_connection(
    cf: Crazyflie,
    clock: Callable[[], float] | None = None,
    report: Callable[[str], None] | None = None,
) -> Any:
    """A ``CrazyflieConnection`` over ``cf`` without a radio to open: its log callbacks are
    called by hand, as cflib would call them."""
    from perchpose.io.crazyflie import CrazyflieConnection

    connection = CrazyflieConnection.__new__(CrazyflieConnection)
    connection.cf = cf
    connection.uri = "radio://0/80/2M/E7E7E7E7E7"
    connection.report = report or (lambda _m: None)
    connection.clock = clock or time.monotonic
    connection.rejected = 0
    connection.gate = SampleGate()
    connection._said = set()
    connection._R_world_body = np.eye(3)
    connection._height_m = None
    connection._odometry = None
    connection._pilots = []
    connection._state_t_s = math.nan
    connection._motion_t_s = math.nan
    connection._f_body_mps2 = None
    connection._gyro = GyroAttitude()
    connection.own_gains = {}
    connection.lean_lag_s = 0.0
    return connection


def state_sample(z_m: float, qw: float = 1.0) -> dict[str, float]:
    """The attitude-and-height log block: level (or ``qw`` spoilt) at ``z_m``."""
    names = ("qw", "qx", "qy", "qz", "z")
    sample = dict(zip([f"stateEstimate.{n}" for n in names], (qw, 0.0, 0.0, 0.0, z_m), strict=True))
    return {**sample, "gyro.x": 0.0, "gyro.y": 0.0, "gyro.z": 0.0}


STILL = {
    **{f"stateEstimate.{a}": 0.0 for a in ("x", "y", "vx", "vy", "vz")},
    "acc.x": 0.0,
    "acc.y": 0.0,
    "acc.z": 1.0,
}


def test_each_state_estimate_sample_ticks_the_pilot(
    crazyflie: tuple[Crazyflie, FakeRadioLink],
) -> None:
    """Between frames the link's odometry log (50 Hz) closes the lateral loop: each sample
    sends a setpoint that steers on it."""
    cf, link = crazyflie
    connection = bare_connection(cf)
    connection._state(0, state_sample(1.0), None)
    connection._moved(0, STILL, None)
    pilot = connection.pilot(VELOCITIES)
    settings = pilot.controller.settings
    seen = Estimate.of_pose(0.0, (0.0, 0.0, 0.5), 0.0)  # upward camera: target straight above
    pilot.update(seen, 0.0)
    frames = len(link.sent)
    assert frames == 1
    vx_frame = decode(link.sent[0])[1]
    connection._moved(0, {**STILL, "stateEstimate.x": 0.006}, None)  # pushed 6 mm along x
    packets = [decode(p) for p in link.sent[frames:]]
    assert len(packets) == 1
    kind, vx, _vy, _vz, _yaw_rate = packets[0]
    assert kind == "velocity"
    assert vx_frame - vx > 0.8 * settings.k_xy * 0.006  # back towards the held target


def test_a_nan_state_sample_is_dropped_and_the_pilot_keeps_steering(
    crazyflie: tuple[Crazyflie, FakeRadioLink],
) -> None:
    """One NaN in either log block: the sample is dropped (said once) and the pilot flies on
    the last good one; every later setpoint still steers towards the target."""
    cf, link = crazyflie
    reports: list[str] = []
    connection = bare_connection(cf, report=reports.append)
    connection._state(0, state_sample(1.0), None)
    connection._moved(0, STILL, None)
    pilot = connection.pilot(VELOCITIES)
    ahead = Estimate.of_pose(0.0, (0.10, 0.0, 0.5), 0.0)  # upward camera: x is the body's front
    for i in range(10):
        pilot.update(replace(ahead, t_s=i / 30), i / 30)
    connection._state(0, state_sample(1.0, qw=math.nan), None)
    connection._moved(0, {**STILL, "stateEstimate.vx": math.nan}, None)
    before = len(link.sent)
    for i in range(10, 40):
        connection._state(0, state_sample(1.0), None)
        connection._moved(0, STILL, None)
        pilot.update(replace(ahead, t_s=i / 30), i / 30)
    sent = link.sent[before:]
    packets = [decode(p) for p in sent if p[0] == CRTPPort.COMMANDER_GENERIC]
    assert len(packets) >= 30
    assert all(p[0] == "velocity" and p[1] > 0.01 for p in packets)  # forward, to the target
    # the fixes go to the Kalman filter beside them, where the odometry says it is
    fixes = [struct.unpack("<fff", p[2]) for p in sent if p[0] == CRTPPort.LOCALIZATION]
    assert len(fixes) >= 20
    assert all(np.isfinite(f).all() for f in fixes)
    assert pilot.replaced_setpoints == 0
    assert connection.rejected == 2
    assert sum("non-finite" in r for r in reports) == 1
    assert pilot.state == "perching"


def test_a_height_that_stops_updating_is_never_contact(
    crazyflie: tuple[Crazyflie, FakeRadioLink],
) -> None:
    """The final climb with the state estimate's log stream frozen mid-climb: a height that
    does not change is no evidence of the plate. The pilot hovers after a quarter of a second
    (no climb) and lands after a second, saying why; the motors are never cut."""
    cf, link = crazyflie
    now = [0.0]
    reports: list[str] = []
    connection = bare_connection(cf, clock=lambda: now[0], report=reports.append)
    pilot = connection.pilot(VELOCITIES, clock=lambda: now[0])
    height = 1.80
    near = Estimate.of_pose(0.0, (-0.015, 0.0, 0.01), 0.0, stage=3)
    for i in range(60):
        now[0] = i / 30
        if i < 12:  # the stream stops 0.4 s in
            height += pilot.controller.settings.commit_speed_mps / 30
            connection._state(0, state_sample(height), None)
            connection._moved(0, STILL, None)
        estimate = replace(near, t_s=now[0]) if i < 3 else None
        pilot.update(estimate, now[0])
    packets = [decode(p) for p in link.sent]
    assert ("stop",) not in packets
    assert all(p[0] == "velocity" and p[1:3] == (0.0, 0.0) for p in packets)
    assert pilot.state == "landing"
    vz = [p[3] for p in packets]
    hover = vz.index(0.0)
    descent = next(i for i, v in enumerate(vz) if v < 0.0)
    assert all(v > 0.0 for v in vz[:hover])  # climbing while the stream was live
    assert all(v == 0.0 for v in vz[hover:descent])
    assert all(v < 0.0 for v in vz[descent:])
    assert 21 <= descent - hover <= 23  # frames from 0.25 s to 1 s after the last sample
    assert any("hovering, no climb" in r for r in reports)
    assert any("landing" in r and "s old" in r for r in reports)


def test_a_live_frame_is_placed_at_its_capture(crazyflie: tuple[Crazyflie, FakeRadioLink]) -> None:
    """A live frame grabbed 0.1 s before the pilot sees its estimate: the pilot's time moves
    on to the capture plus that 0.1 s, and the controller places the fix with the attitude
    the vehicle had at the capture, not the one it has now."""
    cf, _link = crazyflie
    now = [100.0]
    attitude = [np.eye(3)]
    pilot = PerchingPilot(
        CflibCommander(cf.commander),
        lambda: attitude[0],
        report=lambda _m: None,
        clock=lambda: now[0],
    )
    seen = Estimate.of_pose(5.0, (0.05, 0.0, 0.5), 0.0)
    pilot.update(seen, 5.0)  # level at 5.0
    attitude[0] = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # turned 90 deg
    now[0] = 100.2
    live = replace(seen, t_s=5.1, grabbed_s=100.1)  # grabbed 0.1 s ago, while still level
    step = pilot.update(live, 5.1)
    assert pilot.last_t_s == pytest.approx(5.2)
    reference = PerchingController()
    d_level, _ = reference.magnet_to_target(live, np.eye(3))
    assert step.v_mps is not None
    assert np.sign(step.v_mps[0]) == np.sign(d_level[0])  # steered along the level fix's x


def test_reversed_and_implausible_state_samples_are_dropped(
    crazyflie: tuple[Crazyflie, FakeRadioLink],
) -> None:
    """Log blocks stamped before the last one taken (the firmware's milliseconds), or with the
    vehicle tilted 70 degrees, are dropped and said once each; the last good sample stays."""
    cf, _link = crazyflie
    reports: list[str] = []
    connection = bare_connection(cf, report=reports.append)
    connection._state(1000, state_sample(1.0), None)
    connection._moved(1000, STILL, None)
    connection._state(980, state_sample(0.5), None)  # older than the one taken
    connection._moved(990, {**STILL, "stateEstimate.x": 0.3}, None)
    tilted = math.cos(math.radians(35.0))  # a quaternion of 70 degrees about x
    sample = {**state_sample(0.9, qw=tilted), "stateEstimate.qx": math.sin(math.radians(35.0))}
    connection._state(1020, sample, None)
    assert connection.height_m() == 1.0
    odometry = connection.odometry()
    assert odometry is not None
    assert odometry[0][0] == 0.0
    np.testing.assert_allclose(connection.attitude(), np.eye(3))
    assert connection.rejected == 3
    assert connection.gate.refused == {"out of order": 2, "implausible": 1}
    assert sum("out of order" in r for r in reports) == 1
    assert sum("implausible" in r for r in reports) == 1
    connection._state(1040, state_sample(0.95), None)
    assert connection.height_m() == 0.95


class ParamLog:
    """cflib's ``Param`` as the commander uses it: the values it was asked to set, in order
    (``fails``: the link is gone)."""

    def __init__(self, fails: bool = False) -> None:
        self.set: list[tuple[str, str]] = []
        self.fails = fails

    def set_value(self, name: str, value: str) -> None:
        if self.fails:
            raise Exception("Connection timed out")
        self.set.append((name, value))


def test_the_commander_sets_the_firmware_s_velocity_gains_and_gives_back_its_own() -> None:
    """6 /s is 35 deg of tilt per m/s (g tan(theta) ~ g theta); the values read at connection
    go back afterwards. Without them, or on a link that fails, nothing is claimed."""
    own = {"velCtlPid.vxKp": "25.0", "velCtlPid.vyKp": "25.0"}
    params = ParamLog()
    commander = CflibCommander(None, params, own)
    assert commander.set_velocity_gain(6.0)
    assert params.set == [("velCtlPid.vxKp", "35.043"), ("velCtlPid.vyKp", "35.043")]
    commander.restore_velocity_gain()
    assert params.set[2:] == list(own.items())
    assert not CflibCommander(None, ParamLog(), {}).set_velocity_gain(6.0)
    assert not CflibCommander(None, ParamLog(fails=True), own).set_velocity_gain(6.0)


def test_the_accelerometer_is_logged_with_the_odometry_and_leant_against(
    crazyflie: tuple[Crazyflie, FakeRadioLink],
) -> None:
    """``acc.x/y/z`` (g, body frame) come with the odometry block: a push of 0.1 g along the
    body's x on a vehicle yawed 90 deg is a push along the world's y, and the setpoint leans
    against it."""
    cf, link = crazyflie
    now = {"s": 100.0}
    connection = bare_connection(cf, clock=lambda: now["s"])
    yawed = {**state_sample(1.0), "stateEstimate.qw": math.cos(math.pi / 4)}
    yawed["stateEstimate.qz"] = math.sin(math.pi / 4)
    connection._state(0, yawed, None)
    connection._moved(0, STILL, None)
    pilot = connection.pilot(VELOCITIES, clock=lambda: now["s"])
    pilot.update(Estimate.of_pose(0.0, (0.0, 0.0, 0.5), 0.0), 0.0)
    for k in range(1, 11):  # 50 Hz
        now["s"] += 0.02
        connection._moved(20 * k, {**STILL, "acc.x": 0.1}, None)
    f = connection.specific_force()
    assert f is not None
    np.testing.assert_allclose(f, [0.981, 0.0, 9.81], rtol=1e-3)
    _kind, vx, vy, _vz, _yaw_rate = decode(link.sent[-1])
    assert vy < -0.1  # against the push, along world y
    assert abs(vx) < 0.05


class _Params:
    """cflib's ``Param`` as far as the estimator's choice: ``value`` (None: unreadable)."""

    def __init__(self, value: str | None) -> None:
        self.value = value

    def get_value(self, name: str) -> str:
        assert name == "stabilizer.estimator"
        if self.value is None:
            raise KeyError(name)
        return self.value


@pytest.mark.parametrize(
    ("value", "lag_s"), [("2", CRAZYFLIE_KALMAN_LAG_S), ("0", CRAZYFLIE_KALMAN_LAG_S), ("1", 0.0)]
)
def test_the_pilots_take_the_lean_out_of_a_kalman_filters_attitude(
    crazyflie: tuple[Crazyflie, FakeRadioLink], value: str, lag_s: float
) -> None:
    """The Kalman filter (chosen, or the firmware's choice with a Flow deck) misses a push's
    lean: the pilots correct it; the complementary filter's attitude needs nothing."""
    cf, _link = crazyflie
    said: list[str] = []
    cf.param = _Params(value)
    connection = bare_connection(cf, report=said.append)
    connection.lean_lag_s = connection._read_estimator()
    assert connection.lean_lag_s == lag_s
    assert len(said) == (1 if lag_s else 0)
    pilot = connection.pilot()
    assert pilot.settings.lean_lag_s == lag_s
    assert (pilot.lean is not None) == (lag_s > 0)
    own = connection.pilot(settings=PilotSettings(lean_lag_s=0.4))
    assert own.settings.lean_lag_s == 0.4


def test_a_vehicle_that_does_not_say_its_estimator_is_taken_to_fly_the_kalman_filter(
    crazyflie: tuple[Crazyflie, FakeRadioLink],
) -> None:
    cf, _link = crazyflie
    cf.param = _Params(None)
    connection = bare_connection(cf)
    assert connection._read_estimator() == CRAZYFLIE_KALMAN_LAG_S


def test_a_position_fix_goes_out_as_cflibs_external_position(
    crazyflie: tuple[Crazyflie, FakeRadioLink],
) -> None:
    cf, link = crazyflie
    assert CflibCommander(cf.commander).send_position_fix((0.1, -0.2, 1.5)) is False
    assert link.sent == []  # without cflib's Extpos nothing goes out
    commander = CflibCommander(cf.commander, extpos=cf.extpos)
    assert commander.send_position_fix((0.1, -0.2, 1.5)) is True
    ((port, channel, data),) = link.sent
    assert (port, channel) == (CRTPPort.LOCALIZATION, cf.loc.POSITION_CH)
    assert struct.unpack("<fff", data) == pytest.approx((0.1, -0.2, 1.5))


def _decompressed_quaternion(packed: int) -> tuple[float, ...]:
    """The Crazyflie's "smallest three" quaternion (x, y, z, w): the largest component's index
    in the top two bits, the others in 10 bits each (a sign and 9 bits of magnitude up to
    1/sqrt(2)), the last component in the lowest bits."""
    largest = packed >> 30
    q = [0.0, 0.0, 0.0, 0.0]
    squares = 0.0
    for i in (3, 2, 1, 0):
        if i == largest:
            continue
        magnitude, negative = packed & 511, (packed >> 9) & 1
        packed >>= 10
        q[i] = (magnitude / 511) / math.sqrt(2.0) * (-1.0 if negative else 1.0)
        squares += q[i] ** 2
    q[largest] = math.sqrt(max(0.0, 1.0 - squares))
    return tuple(q)


def test_a_full_state_setpoint_goes_out_as_the_firmware_decodes_it(
    crazyflie: tuple[Crazyflie, FakeRadioLink],
) -> None:
    """cflib's own packet (TYPE_FULL_STATE): position in mm, velocity in mm/s, no
    acceleration, the yaw as the orientation's quaternion, no body rates (their units differ
    between cflib and the firmware; the yaw is in the orientation)."""
    cf, link = crazyflie
    CflibCommander(cf.commander).send_full_state((0.1, -0.2, 1.5), (0.05, 0.0, 0.1), 0.3, 0.2)
    ((port, _channel, data),) = link.sent
    assert port == CRTPPort.COMMANDER_GENERIC
    kind, *values, packed, rate_roll, rate_pitch, rate_yaw = struct.unpack("<BhhhhhhhhhIhhh", data)
    assert kind == 6  # TYPE_FULL_STATE
    assert values == [100, -200, 1500, 50, 0, 100, 0, 0, 0]
    x, y, z, w = _decompressed_quaternion(packed)
    assert abs(x) < 0.01
    assert abs(y) < 0.01
    assert 2.0 * math.atan2(z, w) == pytest.approx(0.3, abs=0.01)
    assert (rate_roll, rate_pitch, rate_yaw) == (0, 0, 0)


def test_the_gyro_is_logged_with_the_attitude_and_integrated_on_the_firmwares_clock(
    crazyflie: tuple[Crazyflie, FakeRadioLink],
) -> None:
    """``gyro.x/y/z`` (deg/s) come with the attitude block; the link integrates them over the
    firmware's log timestamps (not their arrival, which bunches), and a Kalman-filter pilot
    holds its attitude to them: a 2 degree jump of the filter's attitude with no turn moves
    the pilot's by the blend's share."""
    cf, _link = crazyflie
    now = {"s": 100.0}
    connection = bare_connection(cf, clock=lambda: now["s"])
    connection.lean_lag_s = CRAZYFLIE_KALMAN_LAG_S
    assert connection.gyro() is None
    for k in range(26):  # 0.5 s of firmware time at 50 Hz, arriving in bursts
        now["s"] = 100.0 + 0.1 * (k // 5)
        connection._state(20 * k, {**state_sample(1.0), "gyro.z": 20.0}, None)
    reading = connection.gyro()
    assert reading is not None
    assert math.degrees(yaw_rad(reading.R_ref_body)) == pytest.approx(10.0, rel=1e-6)
    pilot = connection.pilot(clock=lambda: now["s"])
    assert pilot.blend is not None
    level = pilot._attitude(0.0)
    tilted = {**state_sample(1.0), "stateEstimate.qw": math.cos(math.radians(1.0))}
    tilted["stateEstimate.qx"] = math.sin(math.radians(1.0))  # rolled 2 degrees
    connection._state(20 * 26, tilted, None)  # gyro 0: nothing turned
    after = pilot._attitude(0.1)
    roll_deg = math.degrees(roll_pitch_rad(after)[0] - roll_pitch_rad(level)[0])
    assert 0.0 < roll_deg < 0.1


def test_an_attitude_setpoint_goes_out_as_the_firmware_decodes_it(
    crazyflie: tuple[Crazyflie, FakeRadioLink],
) -> None:
    """cflib's own packet (TYPE_ZDISTANCE): roll and pitch in degrees, the pitch in the
    firmware's legacy sign (a nose-down lean, which accelerates forward, goes out negative:
    the decoder passes it on to a PID that compares it with its own legacy pitch), the yaw
    rate counter-clockwise in deg/s, the height in metres."""
    cf, link = crazyflie
    CflibCommander(cf.commander).send_attitude(math.radians(3.0), math.radians(5.0), 0.2, 1.5)
    ((port, _channel, data),) = link.sent
    assert port == CRTPPort.COMMANDER_GENERIC
    kind, roll, pitch, yaw_rate, z = struct.unpack("<Bffff", data)
    assert kind == 9  # TYPE_ZDISTANCE (today's: the yaw rate counter-clockwise positive)
    assert roll == pytest.approx(3.0, rel=1e-6)
    assert pitch == pytest.approx(-5.0, rel=1e-6)
    assert yaw_rate == pytest.approx(math.degrees(0.2), rel=1e-6)
    assert z == pytest.approx(1.5, rel=1e-6)


def _kind(packet: tuple[int, int, bytes]) -> str:
    """A commander packet's kind: stop, notify_stop, velocity, zdistance or rpyt."""
    port, channel, data = packet
    if port == CRTPPort.COMMANDER:
        return "rpyt"
    if channel == 1:
        return "notify_stop"
    return {0: "stop", 8: "velocity", 9: "zdistance"}[data[0]]


@pytest.mark.parametrize("fault", ["camera-stall", "target-lost", "odometry-stall", "link-loss"])
def test_attitude_setpoints_through_each_fault_one_metre_up(
    crazyflie: tuple[Crazyflie, FakeRadioLink], fault: str
) -> None:
    """``command="attitude"`` over cflib's packet code, 1 m up with the target 0.8 m above the
    camera for 1 s, then 12 s of the pilot's clock at 20 Hz with one fault. A stalled camera
    or a lost target: attitude setpoints hold, then land it (the height asked 0.1 m under the
    estimate: 0.2 m/s over the position gain), and at touchdown the stop. The odometry stops:
    once it is stale the setpoints are velocities (a hover, then the landing's descent). The
    link drops: nothing more is sent."""
    cf, link = crazyflie
    now = [0.0]
    p_m = np.array([0.0, 0.0, 1.0])
    odometry_age = [0.0]
    pilot = PerchingPilot(
        CflibCommander(cf.commander),
        level,
        settings=PilotSettings(command="attitude"),
        height_m=lambda: float(p_m[2]),
        odometry=lambda: (p_m.copy(), np.zeros(3)),
        ages=lambda: SenseAges(0.0, odometry_age[0], odometry_age[0]),
        clock=lambda: now[0],
        report=lambda _m: None,
    )
    pilot.watch_link(cf)
    for i in range(30):
        now[0] = i / 30.0
        pilot.update(Estimate.of_pose(now[0], (0.02, -0.01, 0.8), 0.0), now[0])
    assert {_kind(p) for p in link.sent} == {"zdistance"}
    link.sent.clear()
    landing_heights: list[tuple[float, float]] = []  # (height, height asked) while landing
    if fault == "link-loss":
        cf.connection_lost.call("radio://0/80/2M/E7E7E7E7E7", "Too many packets lost")
    for k in range(1, 241):
        now[0] = 1.0 + 0.05 * k
        if fault == "odometry-stall":
            odometry_age[0] = now[0] - 1.0
        if fault == "target-lost":
            pilot.update(Estimate.none(now[0]), now[0])
        else:
            pilot.tick(now[0])
        if pilot.state == "landing":
            if fault != "odometry-stall" and _kind(link.sent[-1]) == "zdistance":
                z_asked = struct.unpack("<Bffff", link.sent[-1][2])[4]
                landing_heights.append((float(p_m[2]), z_asked))
            p_m[2] = max(0.0, p_m[2] - 0.2 * 0.05)
    kinds = [_kind(p) for p in link.sent]
    if fault == "link-loss":
        assert pilot.state == "link_lost"
        assert kinds == []
    elif fault == "odometry-stall":
        assert [t[2] for t in pilot.transitions] == ["perching", "landing"]
        stale = kinds.index("velocity")  # the position 0.25 s old
        assert 3 <= stale <= 6
        assert set(kinds[stale:]) == {"velocity"}
        _, _, data = link.sent[-1]
        assert struct.unpack("<Bffff", data)[1:] == pytest.approx((0.0, 0.0, -0.2, 0.0))
    else:
        assert [t[2] for t in pilot.transitions] == ["perching", "lost", "landing", "landed"]
        assert kinds[-2:] == ["stop", "notify_stop"]
        assert set(kinds[:-2]) == {"zdistance"}
        assert p_m[2] == 0.0  # stopped on the floor
        assert len(landing_heights) > 50
        for height_m, z_asked in landing_heights:
            assert z_asked == pytest.approx(height_m - 0.1, abs=1e-5)

"""The perching position controller: from the target's estimated pose to velocity setpoints.

It is the same controller the simulation and the vehicle links use. Inputs: an ``Estimate`` (the
target in the camera frame), the mounting (``T_body_camera`` and the magnet's position on the
body) and the vehicle's own attitude ``R_world_body`` (world z up). Output: a world-frame
velocity setpoint (m/s) and a yaw rate (rad/s), which each vehicle's adapter converts
(``perchpose.control.pilot.VehicleCommander``).

Phases: ``search`` (no target yet: hold), ``align`` (centre the magnet under the target and turn
to its heading at constant height), ``climb`` (rise while keeping alignment, slowing near the
plate), ``commit`` (the last centimetres at a constant gentle speed), ``lost`` (target lost:
hold, then descend to re-acquire).

The final climb is entered only on consistent evidence: ``commit_frames`` valid frames in a
row that put the magnet within ``commit_distance_m`` below the target and ``commit_align_m``
of its centre, or, when the camera loses the target (too close to see it), that many valid
frames in a row within ``blind_commit_m`` and twice the align radius. A valid estimate during
the climb that puts the target further than ``commit_exit_m`` above or ``commit_exit_lateral_m``
aside ends it (one outlier frame can neither start nor hold a final climb), and a final climb
that has run ``commit_timeout_s`` without the vehicle's own contact check ending it backs off
(``lost``: hold, then descend to re-acquire). An estimate older than ``max_estimate_age_s`` or
with a non-finite field counts as no target.

Each fix is placed in the world with the vehicle's attitude at the frame's capture time
(``Estimate.t_s``), from a short time-stamped history of the attitudes the controller was
given, and its heading error is carried to now by the yaw turned since: with the attitude of
the moment the frame arrives, a camera's latency turns every fix by however much the vehicle
rolled, pitched and turned in between, and the vehicle oscillates sideways.

With the vehicle's own odometry (``Odometry``: position and velocity from the flight
controller's state estimate, in its own drifting world frame), the controller also

- holds the target's position in that frame from each fresh fix, matched to the odometry at
  the frame's capture time (so the camera's latency does not lag the loop), and steers on it
  between fixes: the last centimetres, where the camera is too close to see, are flown
  closed-loop on odometry (for at most ``hold_target_s``);
- where the odometry comes with all three axes of the accelerometer, runs the inertial filter
  (``control.inertial``: the fixes and the accelerometer): its position of the vehicle now
  replaces the held target's odometry position along x and y, and the odometry's correlated
  velocity error it estimates is added to each setpoint, so that a vehicle whose own loop
  flies a Flow deck's estimate flies the velocity asked for (its disturbance observer then
  works on the filter's velocity, and the capture cone's speed is the filter's);
- rejects disturbances with an observer on the velocity loop (``control.disturbance``: the gap
  between the velocity it asks for and the one the vehicle flies, beyond the loop's own lag:
  wind, a sagging battery, an attitude bias) and an
  integral on the lateral position error (what the odometry cannot see: its own velocity
  bias), both with anti-windup (clamped; the position integral runs only within
  ``integrate_within_m`` of the centre);
- commits only inside a capture cone: the magnet within ``commit_align_m`` of the centre,
  moving sideways slower than ``capture_speed_mps``, and the vehicle leaning less than
  ``max_commit_tilt_deg`` (leaning into a gust further than that, it waits under the plate
  for a lull: the magnet does not seat at a tilt). A final climb that leaves the cone or
  times out backs off (``retreat``: down to ``retry_below_m`` under the target, then align
  again); after ``max_tries`` failed climbs it gives up (``give-up``: the pilot lands).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field, replace
from enum import StrEnum

import numpy as np
from numpy.typing import NDArray

from perchpose.control.disturbance import DisturbanceObserver
from perchpose.control.history import newest_at
from perchpose.control.inertial import InertialSettings, InertialTracker
from perchpose.control.mount import default_T_body_camera
from perchpose.control.position_fix import PositionFixes, PositionFixSettings
from perchpose.control.push import PushFilter
from perchpose.control.time_offset import TimeOffset, TimeOffsetEstimator, TimeOffsetSettings
from perchpose.errors import ControllerConfigError, require_non_negative, require_positive
from perchpose.geometry import angle_diff_rad, clip_norm, lean_deg, wrap_angle_rad, yaw_rad
from perchpose.values import Estimate

Array = NDArray[np.float64]


class Phase(StrEnum):
    """The controller's phases (strings as well, as they appear in files and logs)."""

    SEARCH = "search"
    ALIGN = "align"
    CLIMB = "climb"
    COMMIT = "commit"
    RETREAT = "retreat"
    LOST = "lost"
    GIVE_UP = "give-up"


STEERED = (Phase.ALIGN, Phase.CLIMB, Phase.COMMIT)  # the phases that steer on the target
STALL_FRAMES = 3  # camera periods without a frame after which odometry steering holds height
# the camera timing the closed loop was verified at in simulation (``ControllerSettings``)
MIN_CAMERA_PERIOD_S = 1.0 / 60.0
MAX_CAMERA_PERIOD_S = 1.0 / 15.0
MAX_CAMERA_LATENCY_S = 0.2
MAX_CARRY_S = 0.1  # the longest an odometry sample is carried forward by its velocity
MIN_PHASE_MARGIN_DEG = 30.0  # of each proportional loop (``phase_margin_deg``)


@dataclass(frozen=True)
class ControllerSettings:
    """Gains and limits (SI units).

    k_xy, k_z, k_yaw : proportional gains, 1/s. align_radius_m : lateral error under which the
    vehicle climbs at full rate far from the plate (none beyond twice it); 25 mm: on the
    Crazyflie's Kalman filter the magnet swings 2-4 cm in wind, and a 15 mm radius held it
    under the plate for seconds (moderate wind 92.5 % -> 95.5 % of 200, strong 55.0 % -> 63.3 %
    of 60; the record). cone_slope : nearer the plate that radius narrows to cone_slope times
    the height (the same cone as before within 15 cm of it), down to commit_align_m.
    commit_distance_m : height below the plate where the final constant-speed climb starts;
    nearer than this, a vehicle outside the cone descends at descend_mps instead of holding
    height. commit_speed_mps : that speed. blind_commit_m : losing the target closer than this while
    aligned (the camera is then too close to see it) commits instead of counting as lost
    (without odometry: when the last frames were within twice the align radius; with it:
    within blind_align_m, and the odometry steers the rest). commit_frames : consecutive valid
    frames that must agree before the final climb starts. commit_exit_m, commit_exit_lateral_m :
    a valid estimate putting the target further above or aside than these ends the final climb.
    commit_timeout_s : a final climb still going after this long backs off.
    max_estimate_age_s : estimates older than this (``Estimate.age_s`` plus the time since
    capture) are ignored. hold_s : hover after losing the target before descending at
    descend_mps.

    Timing, for the stability check (``check_timing``): camera_period_s : the camera's frame
    period. camera_latency_s : its latency, capture to estimate. odometry_period_s : the period
    of the vehicle's odometry, on which the lateral loop and the disturbance observer close
    between frames (None: no odometry; every loop then closes through the camera and its
    latency). The verified envelope is 15-60 fps and up to 200 ms of latency.

    With odometry: hold_target_s : how long the target's position held from the last fix is
    flown on. fix_weight : the weight of a new fix against the held position (the target does
    not move; the odometry drifts slowly). onboard_velocity_gain : the flight controller's
    velocity-loop gain, 1/s (its model in the disturbance observer). onboard_delay_s : how much
    later than that first-order loop the vehicle answers a setpoint (the observer's model;
    ``control.disturbance``): 0.1 s. On the Crazyflie firmware's PID an observer without it
    rings and never perches, with 0.03 s half the runs do and from 0.06 s on nearly all; 0.1 s
    keeps a margin above that (benchmarks/notes/simulation.md). onboard_vertical_gain,
    onboard_vertical_delay_s : the same of its vertical loop, which answers sooner (thrust
    needs no tilt first): 5.5 /s and 0.02 s, fitted to the firmware's PID
    (``control.disturbance``). observer_rate : the
    observer's poles, rad/s (0: no observer). commit_observer_rate : its poles during the
    final climb (0: observer_rate): faster there, where a gust has a few tenths of a second to
    push the magnet aside, and the climb ends before the oscillation that a fast observer
    brings across a long approach can build. max_disturbance_xy_mps, max_disturbance_z_mps :
    the largest setpoint offset it may add. push_feedforward : cancel the aerodynamic push the
    accelerometer measures (``Odometry.push_mps2``) as it comes, through a velocity-setpoint
    offset of ``-push / onboard_velocity_gain`` that the observer takes as a known input (it
    then estimates only what the push does not explain): a gust is answered when it pushes,
    not once it has moved the vehicle. push_filter_s : the push's low-pass time constant (the
    propellers' vibration). max_push_mps2 : the largest push cancelled. k_i_xy :
    integral gain on the lateral position error, 1/s^2 (with k_xy, a critically damped loop):
    it removes what the velocity integrator cannot see, a bias of the odometry's own velocity;
    max_integral_xy_mps : its clamp. integrate_within_m : the integral runs only while the
    lateral error is under this (the approach from a far start would wind it up).
    commit_gain : the lateral gain is this many times k_xy during the final climb (the errors
    are small there and the time short, so a stiffer loop holds the magnet on the centre
    without the overshoot it would cause across a long approach). capture_speed_mps : the
    largest sideways speed at which the final climb may start, measured
    over the last speed_window_s of odometry positions. max_commit_tilt_deg : the largest
    tilt (the latest attitude's) at which the final climb may start; leaning further within
    twice ``commit_distance_m`` of the plate, the vehicle stops climbing (and backs down
    within ``commit_distance_m``) until a lull lets it level: in strong wind the tilt that
    holds it against a gust is what a contact at over 15 deg fails on.
    retry_below_m : how far under the target a backed-off climb descends before aligning
    again. max_tries : failed final climbs before giving up.

    time_offset : the online estimate of the camera-to-vehicle time offset
    (``control.time_offset``: what the frames' stamps are off by against the vehicle's samples,
    from the motion both see). correct_time_offset : place each fix at its stamp plus that
    offset while the estimate is trusted (without it the offset is only estimated and
    reported).

    position_fixes : the camera's fixes as the vehicle's position in its odometry frame, for
    its own estimator (``control.position_fix``; ``Command.position_fix_m``).

    inertial : the inertial filter's settings (``control.inertial``; ``enabled`` off: the
    odometry is flown as it comes).
    """

    k_xy: float = 2.5
    commit_gain: float = 1.5
    k_z: float = 0.9
    k_yaw: float = 1.5
    max_xy_mps: float = 0.35
    max_z_mps: float = 0.3
    max_yaw_rate: float = 1.5
    align_radius_m: float = 0.025
    cone_slope: float = 0.1
    commit_distance_m: float = 0.04
    commit_speed_mps: float = 0.15
    commit_align_m: float = 0.004
    blind_commit_m: float = 0.12
    blind_align_m: float = 0.005
    commit_frames: int = 3
    commit_exit_m: float = 0.10
    commit_exit_lateral_m: float = 0.008
    commit_timeout_s: float = 2.0
    max_estimate_age_s: float = 0.5
    hold_target_s: float = 1.0
    onboard_velocity_gain: float = 4.3
    onboard_delay_s: float = 0.1
    onboard_vertical_gain: float = 5.5
    onboard_vertical_delay_s: float = 0.02
    observer_rate: float = 12.0
    commit_observer_rate: float = 18.0
    k_i_xy: float = 1.5
    max_integral_xy_mps: float = 0.1
    integrate_within_m: float = 0.03
    max_disturbance_xy_mps: float = 0.6
    max_disturbance_z_mps: float = 0.3
    push_feedforward: bool = True
    push_filter_s: float = 0.03
    max_push_mps2: float = 4.0
    capture_speed_mps: float = 0.03
    max_commit_tilt_deg: float = 12.0
    speed_window_s: float = 0.1
    retry_below_m: float = 0.15
    max_tries: int = 3
    fix_weight: float = 1.0
    hold_s: float = 1.0
    descend_mps: float = 0.1
    camera_period_s: float = 1.0 / 30.0
    camera_latency_s: float = 1.0 / 30.0
    odometry_period_s: float | None = 0.02
    p_body_magnet_m: tuple[float, float, float] = (0.0, 0.0, 0.035)
    T_body_camera: Array = field(default_factory=default_T_body_camera)
    time_offset: TimeOffsetSettings = field(default_factory=TimeOffsetSettings)
    correct_time_offset: bool = True
    position_fixes: PositionFixSettings = field(default_factory=PositionFixSettings)
    inertial: InertialSettings = field(default_factory=InertialSettings)

    def __post_init__(self) -> None:
        positive = (
            "k_xy",
            "k_z",
            "k_yaw",
            "max_xy_mps",
            "max_z_mps",
            "max_yaw_rate",
            "align_radius_m",
            "cone_slope",
            "blind_align_m",
            "commit_speed_mps",
            "descend_mps",
            "camera_period_s",
            "commit_exit_m",
            "commit_exit_lateral_m",
            "commit_timeout_s",
            "max_estimate_age_s",
            "hold_target_s",
            "capture_speed_mps",
            "max_commit_tilt_deg",
            "speed_window_s",
            "retry_below_m",
            "max_disturbance_xy_mps",
            "max_disturbance_z_mps",
            "max_push_mps2",
            "max_integral_xy_mps",
            "integrate_within_m",
            "onboard_velocity_gain",
            "onboard_vertical_gain",
            "commit_gain",
        )
        require_positive(self, positive, ControllerConfigError)
        require_non_negative(
            self,
            ("onboard_delay_s", "onboard_vertical_delay_s", "push_filter_s"),
            ControllerConfigError,
        )
        if self.commit_frames < 1:
            raise ControllerConfigError(f"commit_frames must be >= 1, got {self.commit_frames}")
        if self.max_tries < 1:
            raise ControllerConfigError(f"max_tries must be >= 1, got {self.max_tries}")
        if not 0 < self.fix_weight <= 1:
            raise ControllerConfigError(f"fix_weight must be in (0, 1], got {self.fix_weight}")
        if self.k_i_xy < 0 or self.k_i_xy > self.k_xy**2:
            raise ControllerConfigError(
                f"k_i_xy must be between 0 and k_xy^2 = {self.k_xy**2:.2f} /s^2 "
                f"(an oscillating loop beyond), got {self.k_i_xy}"
            )
        self.check_timing()

    def check_timing(self) -> None:
        """Refuse a frame rate, latency or gain outside what the simulation verified.

        Each proportional loop (lateral, its final-climb stiffening, vertical, yaw) is modelled
        as its gain around the vehicle's velocity loop (a first-order lag of
        1 / ``onboard_velocity_gain``) seen through the loop's delay, and needs a phase margin
        of 30 deg (``phase_margin_deg``). With odometry the loops and the disturbance observer
        close on it between frames (a delay of two odometry periods), and each fix is placed at
        its capture time, so the camera's latency does not enter them; without odometry every
        loop sees the target ``camera_latency_s`` plus a frame late."""
        period, latency = self.camera_period_s, self.camera_latency_s
        if not (MIN_CAMERA_PERIOD_S - 1e-9 <= period <= MAX_CAMERA_PERIOD_S + 1e-9):
            raise ControllerConfigError(
                f"a camera at {1.0 / period:.3g} fps is outside what was verified "
                f"({1.0 / MAX_CAMERA_PERIOD_S:g}-{1.0 / MIN_CAMERA_PERIOD_S:g} fps)"
            )
        if not 0.0 <= latency <= MAX_CAMERA_LATENCY_S + 1e-9:
            raise ControllerConfigError(
                f"a camera latency of {latency * 1000:.0f} ms is outside what was verified "
                f"(0-{MAX_CAMERA_LATENCY_S * 1000:.0f} ms)"
            )
        odometry = self.odometry_period_s
        if odometry is not None and not odometry > 0.0:
            raise ControllerConfigError(f"odometry_period_s must be positive, got {odometry}")
        # with odometry the loops close at each sample and each frame, whichever comes first
        step = min(odometry, period) if odometry is not None else period
        if odometry is not None:  # the observer runs only on odometry; its step must be stable
            rates = {
                "commit_observer_rate": (self.commit_observer_rate, 1.0),
                "observer_rate": (self.observer_rate, 0.5),
            }
            for name, (rate, bound) in rates.items():
                if not 0 <= rate * step < bound:
                    raise ControllerConfigError(
                        f"{name} = {rate:g} rad/s must be >= 0 and under "
                        f"{bound / step:.1f} rad/s at a {step:.3f} s update period"
                    )
        delay = 2.0 * step if odometry is not None else period + latency
        lag = 1.0 / self.onboard_velocity_gain
        gains = {
            "k_xy": self.k_xy,
            "k_xy * commit_gain": self.k_xy * self.commit_gain,
            "k_z": self.k_z,
            "k_yaw": self.k_yaw,
        }
        for name, gain in gains.items():
            margin = phase_margin_deg(gain, lag, delay)
            if margin < MIN_PHASE_MARGIN_DEG:
                through = (
                    f"{step:.3f} s update period (odometry)"
                    if odometry is not None
                    else f"{period:.3f} s camera period and {latency * 1000:.0f} ms of latency "
                    "(no odometry)"
                )
                raise ControllerConfigError(
                    f"{name} = {gain:g} /s is unstable with a {through}: a phase margin of "
                    f"{margin:.0f} deg (need {MIN_PHASE_MARGIN_DEG:g})"
                )


def phase_margin_deg(gain: float, lag_s: float, delay_s: float) -> float:
    """The phase margin of a proportional position loop around the vehicle's velocity loop,
    ``gain * exp(-s delay) / (s (lag s + 1))``, in degrees."""
    low, high = 0.0, gain  # |L| = 1 at a crossover below the gain itself
    for _ in range(60):
        w = 0.5 * (low + high)
        if gain / (w * math.hypot(1.0, lag_s * w)) > 1.0:
            low = w
        else:
            high = w
    w = 0.5 * (low + high)
    return 90.0 - math.degrees(math.atan(lag_s * w) + w * delay_s)


@dataclass(frozen=True)
class Odometry:
    """The flight controller's own state estimate at ``t_s`` (the moment it describes, which
    a late sample puts before the frame's time): position and velocity in its world frame
    (z up; the origin and a slow drift are its own)."""

    t_s: float
    p_m: Array
    v_mps: Array
    # the aerodynamic push the accelerometer measures (its body x and y specific force, turned
    # into the world frame; z is 0), m/s^2, or None where the link does not stream it
    push_mps2: Array | None = None
    # the accelerometer's sample with it (body frame, all three axes: at rest +g along z),
    # m/s^2, or None where the link does not stream all three
    f_body_mps2: Array | None = None


@dataclass(frozen=True)
class Command:
    """A velocity setpoint in the world frame (z up), a yaw rate, and the phase."""

    v_mps: Array
    yaw_rate_rad_s: float
    phase: Phase
    error_m: Array | None = None
    # the vehicle's position now as this frame's fix says it (odometry frame), for the
    # vehicle's own estimator; None: none to send
    position_fix_m: Array | None = None
    # the vertical speed the phase asks for, before the disturbance rejection's offset
    # (None: the setpoint's own)
    asked_z_mps: float | None = None

    @property
    def climb_asked_mps(self) -> float:
        """The vertical speed the controller asked for (up positive)."""
        return float(self.v_mps[2]) if self.asked_z_mps is None else self.asked_z_mps


def carried(odometry: Odometry, t_s: float) -> Array:
    """The odometry's position carried from its own time to ``t_s`` by its velocity (a
    sample that arrives late describes the vehicle as it was; at most ``MAX_CARRY_S``)."""
    age = min(MAX_CARRY_S, max(0.0, t_s - odometry.t_s))
    carried: Array = np.asarray(odometry.p_m, np.float64) + age * np.asarray(
        odometry.v_mps, np.float64
    )
    return carried


def usable(estimate: Estimate | None, t_s: float, max_age_s: float) -> bool:
    """A valid estimate with finite fields, at most ``max_age_s`` old at ``t_s`` (its own age
    plus the time since its frame was captured)."""
    if estimate is None or not estimate.valid or not estimate.finite:
        return False
    age = estimate.age_s + max(0.0, t_s - estimate.t_s)
    return math.isfinite(age) and age <= max_age_s


class PerchingController:
    """Steers the magnet onto the target's centre; call ``update`` once per camera frame."""

    def __init__(self, settings: ControllerSettings | None = None) -> None:
        self.settings = settings or ControllerSettings()
        self.phase = Phase.SEARCH
        self.tries = 0
        self._lost_since: float | None = None
        self._commit_since: float | None = None
        # magnet-to-target vectors (world frame) of the latest measured frames, newest last
        self._recent: deque[Array] = deque(maxlen=self.settings.commit_frames)
        # odometry: recent positions (to match a frame's capture time), the held target
        self._track: deque[tuple[float, Array]] = deque(maxlen=64)
        # the attitudes given with each frame and odometry sample, to place a late fix
        self._attitudes: deque[tuple[float, Array]] = deque(maxlen=64)
        self._target_odom: Array | None = None
        self._target_t: float | None = None
        # where the inertial filter put the held target (x, y) less where the odometry does,
        # while it was in use since the last fix: carried on if it drops out before the next
        self._inertial_gap: Array | None = None
        self._observer = DisturbanceObserver(
            self.settings.onboard_velocity_gain,
            self.settings.observer_rate,
            (
                self.settings.max_disturbance_xy_mps,
                self.settings.max_disturbance_xy_mps,
                self.settings.max_disturbance_z_mps,
            ),
            self.settings.onboard_delay_s,
            vertical_gain=self.settings.onboard_vertical_gain,
            vertical_delay_s=self.settings.onboard_vertical_delay_s,
        )
        self._integral_xy = np.zeros(2)
        self._steer_t: float | None = None
        self._last_t: float | None = None
        self._last_sp: Array | None = None
        settings = self.settings  # the measured push, low-passed (world frame)
        self._push = PushFilter(
            settings.push_feedforward, settings.push_filter_s, settings.max_push_mps2
        )
        self._tilt_deg = 0.0
        # the last frame's command before the observer's offset (flown on between frames)
        self._frame_command: Command | None = None
        self._frame_t = -math.inf
        self._offset = TimeOffsetEstimator(self.settings.time_offset)
        self.position_fixes = PositionFixes(self.settings.position_fixes)
        self._position_fix: Array | None = None  # this frame's, for its command
        self.inertial = InertialTracker(self.settings.inertial)
        # the pilot flies the horizontal velocity loop itself (attitude setpoints): the
        # setpoint's horizontal velocity is then the one asked, with no offset for a loop
        self._lean_command = False

    def use_lean_command(self, on: bool = True) -> None:
        """The pilot sends attitude setpoints and flies the horizontal velocity loop itself
        (``control.attitude_command``, on ``horizontal_velocity_mps`` and the push): from now
        on the horizontal setpoint is the velocity asked, with none of the offsets that make
        a vehicle's own loop on its own estimate fly it (the estimate's error, the push, the
        observer's); the vertical keeps them. ``on`` False: velocity setpoints again, with
        the offsets."""
        self._lean_command = on

    def horizontal_velocity_mps(self, odometry: Odometry) -> Array:
        """The vehicle's horizontal velocity at the odometry's time: the inertial filter's
        where it knows it, otherwise the odometry's own."""
        known = self.inertial.velocity_at(odometry.t_s)
        v = np.asarray(odometry.v_mps, np.float64)[:2] if known is None else known
        return np.array(v, np.float64)

    def use_velocity_gain(self, gain_per_s: float) -> None:
        """The vehicle's velocity loop now has this gain (the pilot set it): the observer and
        the push's cancellation model it from now on."""
        self.settings = replace(self.settings, onboard_velocity_gain=gain_per_s)
        self._observer.k_v = gain_per_s

    @property
    def time_offset(self) -> TimeOffset | None:
        """The latest estimate of the camera-to-vehicle time offset (None before the first:
        too few fixes, or too little motion to tell)."""
        return self._offset.latest

    def capture_time(self, estimate: Estimate) -> float:
        """When ``estimate``'s frame was captured, on the vehicle's clock: its stamp, plus
        the estimated time offset while that is trusted (``correct_time_offset``)."""
        return estimate.t_s + self.capture_time_correction_s()

    def capture_time_correction_s(self) -> float:
        """What ``capture_time`` adds to a stamp now (0: no trusted estimate, or not asked
        to correct)."""
        return self._offset.correction_s if self.settings.correct_time_offset else 0.0

    @property
    def disturbance_mps(self) -> Array:
        """The disturbance observer's setpoint offset, m/s (world frame)."""
        return self._observer.offset_mps

    @property
    def observer_rate(self) -> float:
        """The disturbance observer's poles in the last update, rad/s
        (``commit_observer_rate`` in the final climb, else ``observer_rate``)."""
        return float(self._observer.rate)

    def magnet_to_target(self, estimate: Estimate, R_world_body: Array) -> tuple[Array, float]:
        """(world-frame vector from the magnet to the target centre, heading error in rad)."""
        s = self.settings
        T = s.T_body_camera
        d_world = R_world_body @ (self._target_in_body(estimate) - np.asarray(s.p_body_magnet_m))
        yaw = estimate.yaw_rad
        x_target_camera = np.array([math.cos(yaw), math.sin(yaw), 0.0])
        x_target_body = T[:3, :3] @ x_target_camera
        heading_error = math.atan2(float(x_target_body[1]), float(x_target_body[0]))
        return d_world, wrap_angle_rad(heading_error)

    def _all_recent(self, height_m: float, lateral_m: float) -> bool:
        """The last ``commit_frames`` measured frames all had the target under ``height_m``
        above and ``lateral_m`` aside."""
        return len(self._recent) == self.settings.commit_frames and all(
            float(d[2]) < height_m and float(np.hypot(d[0], d[1])) < lateral_m for d in self._recent
        )

    def _enter_commit(self, t_s: float) -> None:
        if self.phase != Phase.COMMIT:
            self._commit_since = t_s
        self.phase = Phase.COMMIT

    def back_off(self, t_s: float) -> Phase:
        """Abandon the final climb (no contact came, or it left the capture cone): descend
        under the target and align again (``retreat``), or give up after ``max_tries``."""
        self.tries += 1
        self.phase = Phase.GIVE_UP if self.tries >= self.settings.max_tries else Phase.RETREAT
        self._commit_since = None
        self._lost_since = t_s
        self._recent.clear()
        return self.phase

    # -- the vehicle's past ---------------------------------------------------------------

    def _remember_attitude(self, t_s: float, R_world_body: Array) -> None:
        self._tilt_deg = lean_deg(np.asarray(R_world_body, np.float64))  # the latest attitude's
        self._offset.attitude(t_s, R_world_body)
        if self._attitudes and t_s < self._attitudes[-1][0]:
            return  # out of order: the history stays sorted
        self._attitudes.append((t_s, np.asarray(R_world_body, np.float64)))

    def attitude_at(self, t_s: float, R_now: Array) -> Array:
        """The vehicle's attitude at ``t_s`` from the history (the nearest sample at or
        before it, or the oldest kept); ``R_now`` when there is none."""
        return newest_at(self._attitudes, t_s) if self._attitudes else R_now

    # -- odometry ---------------------------------------------------------------------------

    def _magnet_offset(self, R_world_body: Array) -> Array:
        """The magnet from the body's centre, world frame."""
        offset: Array = R_world_body @ np.asarray(self.settings.p_body_magnet_m, np.float64)
        return offset

    def _magnet_odom(self, p_m: Array, R_world_body: Array) -> Array:
        magnet: Array = np.asarray(p_m, np.float64) + self._magnet_offset(R_world_body)
        return magnet

    def _remember(self, odometry: Odometry) -> None:
        """Add an odometry sample to the history fixes are matched against, and its
        accelerometer's sample to the inertial filter (turned into the world frame by the
        attitude of the sample's time)."""
        self._track.append((odometry.t_s, np.asarray(odometry.p_m, np.float64)))
        f_body = odometry.f_body_mps2
        if f_body is None or not self._attitudes:
            return
        R = newest_at(self._attitudes, odometry.t_s)
        a_world = R @ np.asarray(f_body, np.float64)
        self.inertial.sample(odometry.t_s, a_world[:2], np.asarray(odometry.v_mps)[:2])

    def _velocity_correction(self, t_s: float) -> Array:
        """What the vehicle's own velocity estimate is off by, as the inertial filter sees
        it, carried to ``t_s`` (horizontal; zero where the filter is not in use)."""
        error = self.inertial.odometry_error(t_s)
        if error is None:
            return np.zeros(2)
        return clip_norm(error, self.settings.inertial.max_correction_mps)

    def _target_in_body(self, estimate: Estimate) -> Array:
        """The target's centre in the body frame (m), through the camera's mount."""
        T = np.asarray(self.settings.T_body_camera, np.float64)
        p_body: Array = T[:3, :3] @ estimate.t_m + T[:3, 3]
        return p_body

    def target_above_magnet_m(self, estimate: Estimate) -> float:
        """How far above the magnet the camera puts the target's centre, along the body's z
        axis (m): the plate's distance, from the frame and the mount alone (no attitude)."""
        p_body = self._target_in_body(estimate) - np.asarray(self.settings.p_body_magnet_m)
        return float(p_body[2])

    def _place(self, estimate: Estimate) -> None:
        """Give a measured fix to the time-offset estimate: its stamp, and the target in the
        body frame."""
        self._offset.fix(estimate.t_s, self._target_in_body(estimate))

    def _position_at(self, t_s: float) -> Array | None:
        """The odometry's position at ``t_s`` (interpolated; None before its history)."""
        if not self._track or t_s < self._track[0][0] - 1e-9:
            return None
        previous = self._track[0]
        for sample in self._track:
            if sample[0] >= t_s:
                t0, p0 = previous
                t1, p1 = sample
                w = 0.0 if t1 <= t0 else (t_s - t0) / (t1 - t0)
                return p0 + w * (p1 - p0)
            previous = sample
        return self._track[-1][1]

    def _hold_fix(self, t_capture_s: float, d: Array, R_world_body: Array, p_now_m: Array) -> None:
        """Hold the target's odometry-frame position from a fresh fix captured at
        ``t_capture_s``; the vehicle's position it implies now (``p_now_m``: the odometry's)
        for the vehicle's estimator."""
        r_m = -(d + self._magnet_offset(R_world_body))  # the body's centre from the target
        self.inertial.fix(t_capture_s, r_m[:2], float(np.linalg.norm(d)))
        self._inertial_gap = None  # a fix of its own again
        p_capture = self._position_at(t_capture_s)
        if p_capture is None:
            return
        fix = self._magnet_odom(p_capture, R_world_body) + d
        if self.settings.position_fixes.send:
            self._position_fix = self.position_fixes.fix(fix, p_now_m)
        if self._target_odom is None:
            self._target_odom = fix
        else:
            self._target_odom = self._target_odom + self.settings.fix_weight * (
                fix - self._target_odom
            )
        self._target_t = t_capture_s

    def _sideways_mps(self, odometry: Odometry) -> float:
        """The vehicle's sideways speed: from the odometry's positions over the last
        ``speed_window_s`` (the position integrates the velocity, so the difference averages out
        the velocity's own noise); the odometry's velocity before there is such a history."""
        s = self.settings
        known = self.inertial.velocity_at(odometry.t_s)
        if known is not None:
            return float(np.hypot(known[0], known[1]))
        then = self._position_at(odometry.t_s - s.speed_window_s)
        if then is None:
            return float(np.hypot(odometry.v_mps[0], odometry.v_mps[1]))
        moved = np.asarray(odometry.p_m, np.float64) - then
        return float(np.hypot(moved[0], moved[1])) / s.speed_window_s

    def _held_error(
        self, t_s: float, R_world_body: Array, odometry: Odometry | None, limit_s: float
    ) -> Array | None:
        """Magnet-to-target from the held target and the odometry now, or None."""
        if odometry is None or self._target_odom is None or self._target_t is None:
            return None
        if t_s - self._target_t > limit_s:
            return None
        held = self._target_odom - self._magnet_odom(carried(odometry, t_s), R_world_body)
        state = self.inertial.state_at(t_s)
        if state is not None:
            inertial = -(state[0] + self._magnet_offset(R_world_body)[:2])
            self._inertial_gap = inertial - held[:2]
            held[:2] = inertial
        elif self._inertial_gap is not None:
            # the filter has dropped out (blind too long under the plate, its velocity no
            # longer known): go on from where it left the target, on the odometry's motion,
            # not from where the odometry's own drift has put it (centimetres apart)
            held[:2] += self._inertial_gap
        return held

    def _reject(self, v_cmd: Array, t_s: float, odometry: Odometry | None) -> Array:
        """The velocity setpoint with the disturbance observer's offset added."""
        s = self.settings
        dt = 0.0 if self._last_t is None else min(0.1, max(0.0, t_s - self._last_t))
        self._last_t = t_s
        if odometry is None:
            return v_cmd
        # the vehicle's loop flies its own velocity estimate: where the inertial filter knows
        # that estimate's error, the setpoint carries it (so that the vehicle flies the
        # velocity asked for), and the observer works on the filter's velocity: the
        # estimate's error, and what it does to the loop, are then no disturbance to it
        correction = np.zeros(3)
        correction[:2] = self._velocity_correction(t_s)
        v_flown = np.array(odometry.v_mps, np.float64)
        v_flown[:2] = self.horizontal_velocity_mps(odometry)
        push = self._filtered_push(odometry, dt)
        v_sp = v_cmd - push / s.onboard_velocity_gain
        if s.observer_rate != 0:
            previous = self._last_sp if self._last_sp is not None else np.zeros(3)
            fast = self.phase == Phase.COMMIT and s.commit_observer_rate > 0
            self._observer.rate = s.commit_observer_rate if fast else s.observer_rate
            self._observer.update(previous, v_flown, dt, max(0.0, t_s - odometry.t_s), push)
            v_sp = v_sp + self._observer.offset_mps
            self._last_sp = v_sp
        if self._lean_command:
            return np.array([v_cmd[0], v_cmd[1], v_sp[2]], np.float64)
        return v_sp + correction

    def _filtered_push(self, odometry: Odometry, dt_s: float) -> Array:
        """The push to cancel now: the accelerometer's, low-passed and clamped (zero without
        one, or with ``push_feedforward`` off)."""
        x, y = self._push.update(odometry.push_mps2, dt_s)
        return np.array([x, y, 0.0], np.float64)

    # -- the loop -----------------------------------------------------------------------------

    def update(
        self,
        estimate: Estimate | None,
        t_s: float,
        R_world_body: Array,
        odometry: Odometry | None = None,
        attitude_age_s: float = 0.0,
    ) -> Command:
        """The setpoint for this frame; an estimate that is None, not valid, not finite or too
        old means no target. ``odometry``: the flight controller's latest state estimate.
        ``attitude_age_s``: how long before ``t_s`` the attitude ``R_world_body`` was
        measured (it is kept in the history at that time)."""
        self._remember_attitude(t_s - attitude_age_s, R_world_body)
        if odometry is not None:
            self._offset.position(odometry.t_s, odometry.p_m)
        self._position_fix = None
        command = self._command(estimate, t_s, R_world_body, odometry)
        steered = command.phase in STEERED and command.error_m is not None
        self._frame_command = command if steered else None
        self._frame_t = t_s
        if command.phase in (Phase.SEARCH, Phase.GIVE_UP):
            return command
        return Command(
            self._reject(command.v_mps, t_s, odometry),
            command.yaw_rate_rad_s,
            command.phase,
            command.error_m,
            self._position_fix,
            float(command.v_mps[2]),
        )

    def between_frames(
        self, t_s: float, R_world_body: Array, odometry: Odometry, attitude_age_s: float = 0.0
    ) -> Command | None:
        """The setpoint between camera frames, from a new odometry sample: the lateral loop
        steers on the target held in the odometry frame (the vertical speed, the yaw rate and
        the phase stay the last frame's, which alone decides them). None where there is nothing
        to steer on: no held target, or the last frame did not steer (search, lost, give-up).

        A flight controller reports its state several times per camera frame; closing the
        lateral loop at that rate takes out gusts a frame-rate loop lets through. When no frame
        has come for ``STALL_FRAMES`` camera periods (a stalled camera) the vehicle holds its
        height, except in the final climb, and after ``hold_target_s`` nothing is sent."""
        s = self.settings
        self._remember_attitude(t_s - attitude_age_s, R_world_body)
        self._offset.position(odometry.t_s, odometry.p_m)
        last = self._frame_command
        if last is None or self.phase not in STEERED:
            return None
        self._remember(odometry)
        limit = s.commit_timeout_s if self.phase == Phase.COMMIT else s.hold_target_s
        held = self._held_error(t_s, R_world_body, odometry, limit)
        if held is None:
            return None
        v = np.array(last.v_mps, np.float64)
        v[:2] = self._lateral_mps(held, t_s)
        if self.phase != Phase.COMMIT and t_s - self._frame_t > STALL_FRAMES * s.camera_period_s:
            v[2] = 0.0  # the camera has stalled mid-approach: hold height, stay aligned
        rejected = self._reject(v, t_s, odometry)
        return Command(rejected, last.yaw_rate_rad_s, last.phase, held, asked_z_mps=float(v[2]))

    def _lateral_mps(self, d: Array, t_s: float) -> Array:
        """The lateral velocity command for the magnet-to-target vector ``d``: proportional
        (saturated at ``max_xy_mps``) plus the position integral."""
        s = self.settings
        lateral = float(np.hypot(d[0], d[1]))
        k = s.k_xy * (s.commit_gain if self.phase == Phase.COMMIT else 1.0)
        scale = min(1.0, s.max_xy_mps / max(1e-9, k * lateral))
        return k * np.asarray(d[:2], np.float64) * scale + self._integrate(
            d, t_s, wind=lateral < s.integrate_within_m
        )

    def _command(
        self,
        estimate: Estimate | None,
        t_s: float,
        R_world_body: Array,
        odometry: Odometry | None,
    ) -> Command:
        s = self.settings
        if odometry is not None:
            self._remember(odometry)
        since = self._commit_since
        if self.phase == Phase.COMMIT and since is not None and t_s - since >= s.commit_timeout_s:
            self.back_off(t_s)
        if self.phase == Phase.GIVE_UP:
            return Command(np.zeros(3), 0.0, Phase.GIVE_UP)
        yaw_rate = 0.0
        if usable(estimate, t_s, s.max_estimate_age_s):
            assert estimate is not None
            self._lost_since = None
            measured = estimate.age_s <= 0.0  # a measurement of this frame, not a coasting guess
            if measured:
                self._place(estimate)
            t_capture = self.capture_time(estimate)
            R_capture = self.attitude_at(t_capture, R_world_body)
            d, heading_error = self.magnet_to_target(estimate, R_capture)
            turned = angle_diff_rad(yaw_rad(R_world_body), yaw_rad(R_capture))
            heading_error = wrap_angle_rad(heading_error - turned)
            yaw_rate = float(np.clip(s.k_yaw * heading_error, -s.max_yaw_rate, s.max_yaw_rate))
            if measured:
                self._recent.append(d)
                if odometry is not None:
                    self._hold_fix(t_capture, d, R_capture, carried(odometry, t_s))
            held = self._held_error(t_s, R_world_body, odometry, s.hold_target_s)
            error = held if held is not None else d
            return self._steer(error, yaw_rate, t_s, odometry)
        limit = s.commit_timeout_s if self.phase == Phase.COMMIT else s.hold_target_s
        held = self._held_error(t_s, R_world_body, odometry, limit)
        if held is not None and self.phase in (*STEERED, Phase.RETREAT):
            if self.phase in (Phase.ALIGN, Phase.CLIMB) and not self._all_recent(
                s.blind_commit_m, 2 * s.align_radius_m
            ):
                # a camera dropout mid-approach: hold height and stay aligned on odometry
                command = self._steer(held, 0.0, t_s, odometry, may_commit=False)
                command.v_mps[2] = 0.0
                return command
            return self._steer(held, 0.0, t_s, odometry, blind=True)
        return self._no_target(t_s)

    def _steer(
        self,
        d: Array,
        yaw_rate: float,
        t_s: float,
        odometry: Odometry | None,
        *,
        blind: bool = False,
        may_commit: bool = True,
    ) -> Command:
        """Align, climb, commit or retreat on the magnet-to-target vector ``d``."""
        s = self.settings
        lateral = float(np.hypot(d[0], d[1]))
        height = float(d[2])
        v = np.zeros(3)
        v[:2] = self._lateral_mps(d, t_s)
        if self.phase == Phase.RETREAT:
            if height < s.retry_below_m:
                v[2] = -s.descend_mps
                return Command(v, yaw_rate, Phase.RETREAT, d)
            self.phase = Phase.ALIGN
            self._recent.clear()
        if self.phase == Phase.COMMIT and (
            height > s.commit_exit_m or lateral > s.commit_exit_lateral_m
        ):
            # the evidence says the target is not where the climb is
            if odometry is not None:
                if self.back_off(t_s) == Phase.GIVE_UP:
                    return Command(np.zeros(3), 0.0, Phase.GIVE_UP)
                v[2] = -s.descend_mps
                return Command(v, yaw_rate, Phase.RETREAT, d)
            self.phase = Phase.ALIGN
            self._commit_since = None
        slow = odometry is None or self._sideways_mps(odometry) < s.capture_speed_mps
        level = self._tilt_deg < s.max_commit_tilt_deg
        if self.phase == Phase.COMMIT or (
            may_commit
            and slow
            and level
            and (
                self._all_recent(s.commit_distance_m, s.commit_align_m)
                or (blind and self._all_recent(s.blind_commit_m, s.blind_align_m))
            )
        ):
            self._enter_commit(t_s)
            v[2] = s.commit_speed_mps
            return Command(v, yaw_rate, Phase.COMMIT, d)
        aligned = self._aligned(lateral, height)
        self.phase = Phase.CLIMB if aligned > 0 else Phase.ALIGN
        v[2] = aligned * float(np.clip(s.k_z * height, s.commit_speed_mps, s.max_z_mps))
        if aligned == 0.0 and height < s.commit_distance_m:
            # outside the cone this near the plate, holding height is not enough: the climb's
            # momentum (its speed over onboard_velocity_gain, 35 mm at commit_speed_mps)
            # would carry the vehicle into the plate off-centre
            v[2] = -s.descend_mps
        elif not level and height < 2.0 * s.commit_distance_m:
            # leaning into a gust too far to seat the magnet: wait under the plate for a lull
            v[2] = -s.descend_mps if height < s.commit_distance_m else min(v[2], 0.0)
        return Command(v, yaw_rate, self.phase, d)

    def _aligned(self, lateral_m: float, height_m: float) -> float:
        """The share of the climb rate allowed at this lateral error: 1 inside the capture
        cone, falling to 0 at twice its radius. The cone's radius is ``align_radius_m`` far
        from the plate and narrows as ``cone_slope`` times the height to ``commit_align_m``
        at the plate: nearer the plate, the vehicle climbs only when nearly centred."""
        s = self.settings
        radius = min(s.align_radius_m, max(s.commit_align_m, s.cone_slope * max(0.0, height_m)))
        return float(np.clip(2.0 - lateral_m / radius, 0.0, 1.0))

    def _integrate(self, d: Array, t_s: float, *, wind: bool) -> Array:
        """The lateral position integral, advanced by the time since the last steered frame
        when ``wind`` (no more than a frame's worth across a gap)."""
        s = self.settings
        last, self._steer_t = self._steer_t, t_s
        if last is not None and wind:
            dt = min(0.1, max(0.0, t_s - last))
            self._integral_xy = np.clip(
                self._integral_xy + s.k_i_xy * dt * np.asarray(d[:2], np.float64),
                -s.max_integral_xy_mps,
                s.max_integral_xy_mps,
            )
        return self._integral_xy

    def _no_target(self, t_s: float) -> Command:
        s = self.settings
        if self.phase == Phase.COMMIT:  # the last centimetres: the camera is too close to see
            return Command(np.array([0.0, 0.0, s.commit_speed_mps]), 0.0, Phase.COMMIT)
        if self.phase == Phase.SEARCH:
            return Command(np.zeros(3), 0.0, Phase.SEARCH)
        if self.phase in (Phase.ALIGN, Phase.CLIMB) and self._all_recent(
            s.blind_commit_m, 2 * s.align_radius_m
        ):
            self._enter_commit(t_s)
            return Command(np.array([0.0, 0.0, s.commit_speed_mps]), 0.0, Phase.COMMIT)
        if self._lost_since is None:
            self._lost_since = t_s
        self.phase = Phase.LOST
        self._recent.clear()
        if t_s - self._lost_since < s.hold_s:
            return Command(np.zeros(3), 0.0, Phase.LOST)
        return Command(np.array([0.0, 0.0, -s.descend_mps]), 0.0, Phase.LOST)

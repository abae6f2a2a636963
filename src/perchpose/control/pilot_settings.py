"""The perching pilot's safety settings: its clock, the bound of each input's watchdog, and what
counts as contact and as touchdown."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from perchpose.control.setpoint import SetpointLimits
from perchpose.errors import ControllerConfigError, require_positive

ON_SENSES_LOST = ("land", "release")
COMMANDS = ("velocity", "full-state", "attitude")
# what perches best with the Crazyflie firmware's PID and Kalman filter in the loop
# (docs/simulation.md); a MAVLink autopilot is sent velocities whatever is asked
DEFAULT_COMMAND = "attitude"


@dataclass(frozen=True)
class PilotSettings:
    """Safety limits (SI units).

    The clock: setpoint_period_s : the pilot ticks at least this often on its own clock
    (``perchpose.control.pilot_clock.PilotClock``), frames or none.

    The watchdogs (each input's bound):

    - camera: frame_timeout_s : no frame handed over this long (a stalled camera, a stalled
      estimator) and the pilot flies on as if each tick were a frame without the target: the
      controller holds height on odometry, then ``lost``; land_after_lost_s : a target lost
      this long (no frames counted) lands the vehicle;
    - attitude, position, height: stale_after_s : a sample older than this stops the climb
      (the pilot hovers until it is fresh); senses_lost_after_s : older than this, the pilot
      lands or releases the vehicle (``on_senses_lost``: ``land`` for the Crazyflie,
      ``release`` for an autopilot, whose own modes then fly it); while landing, an autopilot
      is handed its own LAND;
    - link: the vehicle link's own (cflib's link loss; a MAVLink HEARTBEAT timeout).

    The landing: land_speed_mps : descent speed. Touchdown, the only end of a landing, is a live
    height under landed_height_m (above the height source's zero) that moved less than
    touchdown_still_m over touchdown_window_s, with the vertical speed (where known) under
    touchdown_speed_mps. stuck_report_s : a landing not yet touched down is said again this
    often (the motors stay on).

    Contact: contact_window_s, contact_rise_m : contact is a final climb whose height rose less
    than contact_rise_m over the last contact_window_s; or a climb at the final climb's speed or
    faster with the plate within climb_contact_within_m by the camera, once it has gone on for a
    contact window (a pose whose latency is under-stated puts the plate further than it is, and
    the magnet seats before the final climb begins); not in the final climb while a fresh frame
    of the last contact window put the plate further than contact_veto_m (a climb that stalls,
    or a height that dips, centimetres under the plate is not against it). live_height_s :
    contact and touchdown count only height samples younger than this (a stream at 10 Hz or
    faster stays live between its samples); it must be shorter than the contact window, so that
    a height that froze never makes a contact on its own. held_window_s, held_still_m,
    held_within_m, held_height_m : contact is also, in any phase with the plate within
    held_within_m by the camera's last measured frame (the magnet reaches about that far) or
    the height within held_height_m of the plate's by the measured frames (each one's distance
    plus the height at its capture: a climb the magnet caught after the camera's last frame),
    a height that stayed within held_still_m over held_window_s while the vertical speeds
    asked for would have moved the vehicle that far in each half of it, and still within
    held_height_m of the plate's; held_height_m is the height sensor's error, not the
    magnet's reach (a Flow deck's range 2 m from the floor reads within 2.5 cm, 1 sigma, and
    the filter fusing it was 3 cm high for tenths of a second before the plate in traced
    runs); held_gap_m : a measured frame
    that puts the plate further than this above the magnet starts that window again: the
    camera sees a gap, which the magnet's pull closes by itself only under about this (0.8 N at
    15 mm against the 39 g vehicle's 0.38 N; 0.26 N at 20 mm, where a vehicle asked to descend
    can hang under the plate for a second, and falls if its motors stop):
    the magnet holds it (the controller backing off, or stepping down out of its capture cone
    and climbing again, on the camera's evidence at a few centimetres; a vehicle in free air
    follows what it is asked with a lag of a few tenths of a second, hence the longer window;
    a vehicle in strong turbulence can fail to follow for as long, but not with the plate that
    near). caught_window_s : with the camera's last measured frame putting the plate within
    held_within_m no longer than two of these windows ago (the vehicle was at the plate a
    moment before), the same evidence over this shorter window, and a height that moved
    against the asking also counts (a Kalman filter's height drifts while the plate holds
    the vehicle: 5 cm up in 0.6 s in a traced run). A held vehicle's own loops tip it over
    (its filter's velocity drifts, its velocity loop leans against the drift), and 0.7-1 s
    after the magnet caught it off-centre a rotor met the plate in traced runs; the whole
    held window stays for a vehicle at the plate's height by its height sensor alone, which
    may be beside the plate descending slower than asked. rigid_window_s, rigid_spread_mps2 :
    either way, where the link gives the accelerometer, held also needs the vehicle rigid:
    its vertical specific force spread less than rigid_spread_mps2 (standard deviation) over
    the last rigid_window_s (``control.evidence.RigidDetector``). The plate takes a held
    vehicle's changes of thrust; a vehicle in free air, whose filter's velocity drifts in a
    gust so that it holds a height against a descent, takes them as acceleration (a vehicle
    0.65 m beside the plate, 2 m up, read held in a traced strong-wind run; its accelerometer
    spread 1.7 m/s^2 over 0.3 s; another, 0.36 m beside it, 0.57-0.60; held vehicles'
    0.12-0.30, and 1.4 just after the magnet seated). It must sit above the accelerometer's
    own spread on the vehicle held still with its motors running (its vibration): 0.2 m/s^2
    in the simulation; on a Crazyflie, log ``acc.z`` with the vehicle held against the plate,
    motors on. held_level_deg : without the camera's recent word (the caught window's), held
    also needs the vehicle level within this tilt: the magnet holds it flat against the plate
    (traced: 0.3-4.5 deg at 8 of 9 such stops, 10 deg at one caught 22 mm off-centre),
    while a vehicle in free air holding its place against strong wind leans into it (the two
    read held beside the plate: 7-11 deg). Set under the tilt at which the magnet holds the
    vehicle, a held vehicle never reads held on that path.

    The magnet's hold (``control.seat_check``): seat_check_s, seat_check_thrust,
    seat_check_mps, seat_fall_mps2, seat_drop_m : contact evidence does not stop the motors
    at once. For seat_check_s the pilot first sends a level thrust of seat_check_thrust of the
    hover's (where the link takes one: cflib's legacy setpoint), else a descent at
    seat_check_mps. It stops the motors only if the vehicle stayed: its accelerometer's
    vertical specific force never read under seat_fall_mps2 twice running (held by the plate
    it reads about g; let go on a quarter of the hover thrust, about a quarter of g), and its
    height (fitted over the last tenths of a second) stayed within seat_drop_m of where the
    check began. A vehicle that came down is not held by the magnet (its gear against the plate
    beyond the magnet's hold, or beside the plate): the controller backs off for another final
    climb. A descent asked of the vehicle's own loop takes off only what its loop's floor
    lets it (the firmware's PID: ``thrustMin`` 20000 of a 42600 hover for 39 g), so a gear
    beyond the hold still reads held: hence the thrust. A knife-edge hold passes even so: a
    gear pressed 23 mm off the magnet's centre in a traced run (a pull of 0.44 N against the
    39 g vehicle's 0.38 N) stayed on a quarter of the hover thrust and fell from the plate
    within 0.3 s of the motors' stop, sliding off in the wind. seat_drop_m sits above the
    wander of a Flow deck's filtered height 2 m from the floor while the plate holds the
    vehicle (3 cm in 0.4 s traced) and under what a vehicle let go on a descent falls in the
    window. seat_check_s 0 stops the motors on the contact evidence alone.
    limits : the largest setpoint sent.

    The vehicle's loop: velocity_gain_per_s : the horizontal velocity-loop gain (1/s) the pilot
    sets on the vehicle when it takes over, where its commander can
    (``VelocityGainSetter``: the Crazyflie's ``velCtlPid.vxKp/vyKp``), and gives back when it
    stops the motors or hands the vehicle back; None leaves the vehicle's own. A stiffer loop
    holds the magnet against gusts; the stock Crazyflie's 25 deg per m/s is about 4.3 /s, 6 /s
    is 35 deg per m/s. Where it cannot be set, the controller keeps modelling the vehicle's
    own gain (``ControllerSettings.onboard_velocity_gain``). Where the vehicle's estimator
    models no drag (``lean_lag_s`` > 0) the vehicle's own gain is kept: its velocity errs with
    the gusts' push, and a stiffer (or softer) loop perched less often on the Crazyflie's
    Kalman filter.

    command : what the pilot sends (``attitude`` unless set: it perches best with the
    Crazyflie firmware's own loops and Kalman filter in the loop): ``velocity`` (a world
    velocity and a yaw rate: cflib's
    ``send_velocity_world_setpoint``, the vehicle's velocity loop flies it) or ``full-state``
    (a position and a yaw in the frame of the vehicle's own estimate, with the velocity:
    cflib's ``send_full_state_setpoint``; the vehicle's position loop then holds it between
    setpoints, on its own estimate at its own rate). The position leads the vehicle's estimate
    by the velocity over position_gain_per_s, and the yaw by the yaw rate over yaw_gain_per_s
    (the vehicle's position and yaw gains: the Crazyflie firmware's ``posCtlPid.xKp`` 2 /s and
    ``pidYaw.kp`` 6 /s), so that its loops fly the pilot's velocity and yaw rate. Or
    ``attitude`` (a roll, a pitch, the yaw rate and a height in the frame of the vehicle's
    own estimate: cflib's ``send_zdistance_setpoint``): the vehicle's attitude loop flies the
    lean and its position loop the height, led by the vertical velocity over
    position_gain_per_s, and the horizontal velocity loop is the pilot's own
    (``control.attitude_command``), lean_gain_per_s on the velocity the camera's fixes and the
    accelerometer give, less the accelerometer's push, within max_lean_deg. A vehicle whose
    link takes velocity setpoints only (a MAVLink autopilot's, here) is sent those, and the
    pilot says so once; so is one whose odometry is missing or older than stale_after_s.
    lean_response_s, lean_follow_window_s, lean_follow_error_deg : a vehicle sent attitudes
    holds its own attitude estimate at the lean sent, as a loop answering over about
    lean_response_s (the Crazyflie firmware's attitude loop: 63 % of a step in 0.15 s); where
    its roll or pitch stood more than lean_follow_error_deg from that on average over about
    the last lean_follow_window_s and turned against it (the plate's touch aside), it does not
    fly what is sent (an angle's sign taken otherwise): the pilot says so and sends velocities
    from then on (``control.lean_follow``).

    lean_lag_s : the vehicle's attitude estimate is drag-free (a flying Crazyflie's Kalman
    filter) and misses the lean a push needs, taken in over about this long: the pilot takes
    that lean, predicted from the accelerometer's push, out of each attitude it uses
    (``control.lean``); 0: the estimate knows its tilt. gyro_blend_s : on such an estimate,
    where the link hands the pilot the vehicle's gyro, the attitude the pilot uses follows the
    integrated gyro over this long and the estimate (its lean taken out) beyond
    (``control.gyro``): the lean's prediction leaves errors that change faster than this.
    """

    land_after_lost_s: float = 4.0
    land_speed_mps: float = 0.2
    landed_height_m: float = 0.05
    touchdown_window_s: float = 0.5
    touchdown_still_m: float = 0.02
    touchdown_speed_mps: float = 0.05
    stuck_report_s: float = 5.0
    contact_window_s: float = 0.3
    contact_rise_m: float = 0.005
    climb_contact_within_m: float = 0.1
    contact_veto_m: float = 0.06
    held_window_s: float = 1.0
    caught_window_s: float = 0.6
    held_still_m: float = 0.02
    held_within_m: float = 0.03
    held_height_m: float = 0.05
    held_gap_m: float = 0.015
    rigid_window_s: float = 0.3
    rigid_spread_mps2: float = 0.4
    held_level_deg: float = 6.0
    seat_check_s: float = 0.4
    seat_check_mps: float = 0.5
    seat_drop_m: float = 0.06
    seat_check_thrust: float = 0.25
    seat_fall_mps2: float = 6.0
    setpoint_period_s: float = 0.05
    frame_timeout_s: float = 0.25
    stale_after_s: float = 0.25
    senses_lost_after_s: float = 1.0
    live_height_s: float = 0.2
    on_senses_lost: str = "land"
    limits: SetpointLimits = field(default_factory=SetpointLimits)
    velocity_gain_per_s: float | None = 6.0
    command: str = DEFAULT_COMMAND
    position_gain_per_s: float = 2.0
    yaw_gain_per_s: float = 6.0
    lean_gain_per_s: float = 8.0
    max_lean_deg: float = 20.0
    lean_lead_s: float = 0.04
    lean_response_s: float = 0.15
    lean_follow_window_s: float = 0.3
    lean_follow_error_deg: float = 10.0
    lean_lag_s: float = 0.0
    gyro_blend_s: float = 3.0

    def __post_init__(self) -> None:
        positive = (
            "land_after_lost_s",
            "land_speed_mps",
            "landed_height_m",
            "touchdown_window_s",
            "touchdown_still_m",
            "touchdown_speed_mps",
            "stuck_report_s",
            "contact_window_s",
            "contact_rise_m",
            "climb_contact_within_m",
            "contact_veto_m",
            "held_window_s",
            "caught_window_s",
            "held_still_m",
            "held_within_m",
            "held_height_m",
            "held_gap_m",
            "rigid_window_s",
            "rigid_spread_mps2",
            "held_level_deg",
            "seat_check_mps",
            "seat_drop_m",
            "seat_fall_mps2",
            "setpoint_period_s",
            "frame_timeout_s",
            "stale_after_s",
            "senses_lost_after_s",
            "live_height_s",
            "position_gain_per_s",
            "yaw_gain_per_s",
            "lean_gain_per_s",
            "max_lean_deg",
            "lean_response_s",
            "lean_follow_window_s",
            "lean_follow_error_deg",
            "gyro_blend_s",
        )
        require_positive(self, positive, ControllerConfigError, "pilot setting ")
        if not (math.isfinite(self.lean_lag_s) and 0.0 <= self.lean_lag_s <= 10.0):
            raise ControllerConfigError(
                f"pilot setting lean_lag_s must be within 0-10 s, got {self.lean_lag_s}"
            )
        if not (math.isfinite(self.lean_lead_s) and 0.0 <= self.lean_lead_s <= 0.5):
            raise ControllerConfigError(
                f"pilot setting lean_lead_s must be within 0-0.5 s, got {self.lean_lead_s}"
            )
        if not (math.isfinite(self.seat_check_thrust) and 0.0 < self.seat_check_thrust < 1.0):
            raise ControllerConfigError(
                "pilot setting seat_check_thrust must be within 0-1 (of the hover's thrust), "
                f"got {self.seat_check_thrust}"
            )
        if not (math.isfinite(self.seat_check_s) and 0.0 <= self.seat_check_s <= 5.0):
            raise ControllerConfigError(
                f"pilot setting seat_check_s must be within 0-5 s, got {self.seat_check_s}"
            )
        if not self.max_lean_deg <= 45.0:
            raise ControllerConfigError(
                f"pilot setting max_lean_deg must be at most 45 deg, got {self.max_lean_deg}"
            )
        if self.command not in COMMANDS:
            raise ControllerConfigError(
                f"pilot setting command {self.command!r}: choose {', '.join(COMMANDS)}"
            )
        gain = self.velocity_gain_per_s
        if gain is not None and not 0.5 <= gain <= 12.0:
            raise ControllerConfigError(
                f"pilot setting velocity_gain_per_s must be within 0.5-12 /s (a vehicle's "
                f"velocity loop), got {gain}"
            )
        if self.on_senses_lost not in ON_SENSES_LOST:
            raise ControllerConfigError(
                f"pilot setting on_senses_lost {self.on_senses_lost!r}: choose "
                f"{' or '.join(ON_SENSES_LOST)}"
            )
        if not self.live_height_s < self.contact_window_s:
            raise ControllerConfigError(
                f"pilot setting live_height_s ({self.live_height_s:g} s) must be below "
                f"contact_window_s ({self.contact_window_s:g} s): a frozen height would read as "
                "contact"
            )
        if not self.stale_after_s < self.senses_lost_after_s:
            raise ControllerConfigError(
                f"pilot setting stale_after_s ({self.stale_after_s:g} s) must be below "
                f"senses_lost_after_s ({self.senses_lost_after_s:g} s)"
            )
        if not self.setpoint_period_s < self.frame_timeout_s:
            raise ControllerConfigError(
                f"pilot setting setpoint_period_s ({self.setpoint_period_s:g} s) must be below "
                f"frame_timeout_s ({self.frame_timeout_s:g} s): the camera's watchdog is read "
                "on the pilot's ticks"
            )

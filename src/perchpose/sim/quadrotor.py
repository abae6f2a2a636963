"""A small quadrotor: rigid body, four rotors whose speed follows its command with a first-order
lag, the aerodynamic wrench of the air moving past it, and the onboard attitude and velocity
loops of a flight controller such as the Crazyflie's.

World frame: x, y horizontal, z up (metres). Body frame: x forward, y left, z up. Rotors in
an X: front-left, front-right, back-right, back-left; front-left and back-right turn so that
their drag torque yaws the body positively (RotorPy's convention).

Forces, body frame, with ``a`` the air's velocity relative to the body (vehicle velocity minus
wind) and ``a_i = a + omega x r_i`` its value at rotor ``i`` (hub position ``r_i``):

- thrust ``k_thrust * w_i^2`` along body z for rotor speed ``w_i`` (rad/s);
- rotor drag (the H-force) ``-w_i * diag(k_d, k_d, k_z) a_i`` at each hub: linear in airspeed
  and in rotor speed, as identified for the Crazyflie 2.0 by Forster (2015, ETH Zurich,
  "System Identification of the Crazyflie 2.0 Nano Quadrocopter");
- body (parasitic) drag ``-|a| diag(c_xy, c_xy, c_z) a`` at the centre of mass;
- the ceiling effect under the plate (thrust gain ``1 / (1 - (r / 4d)^2)`` for the share of
  each rotor's disc the plate covers).

This is the wrench of RotorPy's ``Multirotor`` (Folk et al., 2023) without flapping and
translational lift, which RotorPy's own Crazyflie parameters leave at zero; a test flies both
with the same rotor commands and wind.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from perchpose.errors import VehicleConfigError
from perchpose.geometry import leaned, rot_z

Array = NDArray[np.float64]
GRAVITY_MPS2 = 9.81
# the accelerometer's low-pass, Hz: the cut-off of the filter the Crazyflie firmware runs on its
# IMU's accelerometer, and PX4's default (IMU_ACCEL_CUTOFF)
ACCEL_CUTOFF_HZ = 30.0


@dataclass(frozen=True)
class QuadrotorParams:
    """Defaults: a Crazyflie 2.1 carrying an FPV camera and a magnet (39 g, as in the paper).

    inertia_kg_m2 : diagonal of the inertia tensor. arm_m : rotor hub offset along body x and
    y. max_thrust_n : per rotor. motor_tau_s : first-order time constant of the rotor speed.
    k_thrust : thrust per squared rotor speed, N/(rad/s)^2. yaw_moment_m : drag torque per
    newton of thrust. rotor_drag_kg_per_rad, inflow_drag_kg_per_rad : the H-force's in-plane
    and axial coefficients (k_d, k_z), N per (m/s of airspeed x rad/s of rotor speed).
    body_drag_n_per_mps2 : quadratic body drag along body x/y and z. prop_radius_m : the
    rotor discs' radius. rotor_plane_m : the rotor plane's height above the centre of mass
    (where the ceiling effect acts on each rotor, and what a tilted vehicle may strike the
    plate with; ``perchpose.sim.contact``).

    k_thrust, yaw_moment_m (k_m / k_thrust), k_d and k_z are RotorPy's Crazyflie values
    (k_d, k_z from Forster 2015). Neither source identifies the body drag of a Crazyflie; the
    default is 0.5 rho C_d A with C_d = 1 and the side (15 cm^2) and top (30 cm^2) areas of
    the airframe with its camera and magnet: it matters only at the strongest winds.
    """

    mass_kg: float = 0.039
    inertia_kg_m2: tuple[float, float, float] = (1.66e-5, 1.66e-5, 2.93e-5)
    arm_m: float = 0.0325
    max_thrust_n: float = 0.16
    motor_tau_s: float = 0.03
    k_thrust: float = 2.3e-8
    yaw_moment_m: float = 7.8e-10 / 2.3e-8
    rotor_drag_kg_per_rad: float = 10.2506e-7
    inflow_drag_kg_per_rad: float = 7.553e-7
    body_drag_n_per_mps2: tuple[float, float] = (9.2e-4, 1.8e-3)
    prop_radius_m: float = 0.0235
    rotor_plane_m: float = 0.012

    def __post_init__(self) -> None:
        if not self.mass_kg > 0:
            raise VehicleConfigError(f"mass must be positive, got {self.mass_kg} kg")
        if not all(i > 0 for i in self.inertia_kg_m2):
            raise VehicleConfigError("every inertia must be positive")
        if not (
            self.arm_m > 0 and self.motor_tau_s > 0 and self.max_thrust_n > 0 and self.k_thrust > 0
        ):
            raise VehicleConfigError(
                "arm, motor time constant, max thrust and thrust coefficient must be positive"
            )
        drags = (
            self.rotor_drag_kg_per_rad,
            self.inflow_drag_kg_per_rad,
            *self.body_drag_n_per_mps2,
        )
        if not all(d >= 0 for d in drags):
            raise VehicleConfigError("drag coefficients cannot be negative")
        ratio = 4 * self.max_thrust_n / (self.mass_kg * GRAVITY_MPS2)
        if ratio < 1.2:
            raise VehicleConfigError(
                f"thrust-to-weight {ratio:.2f} is too low to fly (need at least 1.2)"
            )

    @property
    def weight_n(self) -> float:
        """Weight in newtons."""
        return self.mass_kg * GRAVITY_MPS2

    @property
    def max_rotor_speed_rad_s(self) -> float:
        return math.sqrt(self.max_thrust_n / self.k_thrust)


@dataclass(frozen=True)
class OnboardGains:
    """The flight controller's loops: velocity -> attitude -> rate -> torque.

    The horizontal velocity gains are the Crazyflie firmware's velocity PID
    (``position_controller_pid.c``: kp 25 deg of tilt per m/s, ki 1 deg per m), in SI: a tilt
    of theta gives g tan(theta) of acceleration, so 25 deg per m/s is about 4.3 /s and 1 deg
    per m about 0.17 /s^2. Vertically, the firmware's ``pidVZ`` (kp 25 and ki 15 of the motors'
    units per m/s, 1000 to the unit) near the hover is about 6 /s and 4 /s^2; as there, its
    thrust is the collective, not divided by the tilt's cosine (a lean sinks the vehicle until
    the integral makes up the lift lost), and it is added to ``thrust_base_n``, the PID's
    ``thrustBase`` (36000 of 65535, 60 g at full): the integral holds the rest of the weight.
    A setpoint of another kind than the last (velocity, height and lean, level thrust,
    position) zeroes the integrals, as the firmware's PID reinitialises on a mode change
    (``controller_pid.c``): the vehicle sinks until the integral has made up the weight again,
    within 10 mm of the firmware's sink at a take-over and of its height through a 20 deg lean.
    The attitude loop is the firmware's attitude PID (``attitude_pid_controller.c``,
    ``platform_defaults_cf2.h``: ``pidRoll`` and ``pidPitch`` kp 6, ki 3, the integral within
    20 deg s), on the rotation's error instead of Euler angles: it leans as the firmware's PID
    does within 0.1 deg over the first second of a 5 deg step, and the velocity step's rise and
    overshoot follow (``benchmarks/bench_agreement.py``).
    """

    k_velocity: float = 4.3  # 1/s
    k_velocity_z: float = 6.0  # 1/s
    # integral of the velocity error, 1/s^2 (horizontal, vertical), and its clamp in m/s^2: as
    # the Crazyflie's and PX4's velocity PIDs, it trims out a steady push and the battery
    k_velocity_i: tuple[float, float] = (0.17, 4.0)
    max_velocity_i_mps2: float = 3.0
    max_tilt_rad: float = math.radians(20.0)
    k_attitude: float = 6.0  # 1/s
    # the attitude error's integral, 1/s^2, and its clamp (0: none)
    k_attitude_i: float = 3.0
    attitude_i_limit: float = math.radians(20.0)  # rad s
    k_rate: float = 0.004  # N m / (rad/s) per unit inertia scale
    k_yaw_rate: float = 0.0008
    max_rate_rad_s: float = 6.0
    # a full-state setpoint's position loop, as the Crazyflie firmware's PID flies it
    # (``posCtlPid.xKp`` 2 /s, its output capped at 1.1 x 1 m/s; the yaw held with the attitude
    # loop's ``pidYaw.kp`` 6 /s)
    k_position: float = 2.0  # 1/s
    k_height_i: float = 0.5  # 1/s^2: the height's integral (``posCtlPid.zKi``)
    max_position_speed_mps: float = 1.1
    k_yaw: float = 6.0  # 1/s
    # the height loop's thrust divided by the tilt's cosine (False: as the firmware's PID)
    tilt_compensated: bool = False
    thrust_base_n: float = 36000 / 65535 * 0.060 * GRAVITY_MPS2


def mixer(params: QuadrotorParams) -> Array:
    """(4, 4) matrix from motor thrusts to [thrust, torque_x, torque_y, torque_z]."""
    a, k = params.arm_m, params.yaw_moment_m
    # motors: front-left (+a, +a), front-right (+a, -a), back-right (-a, -a), back-left (-a, +a)
    # spin: FL and BR drag the body to positive yaw, FR and BL to negative
    return np.array(
        [
            [1.0, 1.0, 1.0, 1.0],
            [a, -a, -a, a],  # roll torque = sum(y_i f_i)
            [-a, -a, a, a],  # pitch torque = -sum(x_i f_i)
            [k, -k, k, -k],
        ]
    )


Vec3 = tuple[float, float, float]
Mat3 = tuple[Vec3, Vec3, Vec3]


@dataclass(frozen=True)
class PositionHold:
    """A full-state setpoint as the vehicle flies it: the position to hold (the world frame
    of its own estimate, m), the yaw (rad), its own position estimate when the setpoint's
    block of steps began (carried by its velocity estimate through the block, where its
    estimator does not give one step by step), and the velocity sent with them."""

    p_m: Vec3
    yaw_rad: float
    p_estimate_m: Vec3
    v_mps: Vec3 = (0.0, 0.0, 0.0)  # the setpoint's velocity (a feed-forward some loops take)


@dataclass(frozen=True)
class AttitudeHold:
    """An attitude setpoint as the vehicle flies it (cflib's ``send_zdistance_setpoint``): the
    roll and pitch to lean to (rad, the body's ZYX Euler angles under its own heading: pitch
    positive tilts the nose down, towards +x; roll positive lowers the right side, towards
    -y), the yaw rate (rad/s, counter-clockwise), the height to hold (world z of the
    vehicle's own estimate, m) with its position loop, and its own position estimate when the
    setpoint's block of steps began."""

    roll_rad: float
    pitch_rad: float
    yaw_rate_rad_s: float
    z_m: float
    p_estimate_m: Vec3
    # cflib's legacy ``send_setpoint`` instead: the collective thrust as a fraction of the
    # hover's, and no height loop (``z_m`` unused)
    thrust_fraction: float | None = None


Hold = PositionHold | AttitudeHold


def setpoint_mode(hold: Hold | None) -> str:
    """The kind of setpoint a vehicle holding ``hold`` flies (None: a velocity)."""
    if hold is None:
        return "velocity"
    if isinstance(hold, PositionHold):
        return "position"
    return "height" if hold.thrust_fraction is None else "thrust"


class OnboardEstimate(Protocol):
    """A flight controller's state estimator in the loop (``sim.onboard_kalman``): what the
    onboard loops fly, advanced after each physics step with the vehicle's true state."""

    velocity: Vec3  # world frame, m/s
    position: Vec3  # world frame, m
    attitude: Mat3  # R_world_body

    def advance(self, dt_s: float, vehicle: Quadrotor) -> None: ...


class PlateWrench(Protocol):
    """What a surface near the vehicle adds to its dynamics (``perchpose.sim.contact``)."""

    def substeps(self, p: Vec3, R: Mat3) -> int: ...

    def wrench(self, p: Vec3, v: Vec3, R: Mat3, w: Vec3) -> tuple[Vec3, Vec3] | None: ...


class Quadrotor:
    """The vehicle's state and its integration. ``p_m``, ``v_mps`` in the world frame;
    ``R_world_body``; ``omega_rad_s`` in the body frame; ``rotor_speed_rad_s`` per rotor.

    ``wind_mps`` (world frame) is the air's velocity at the vehicle; ``thrust_scale`` per rotor
    is what each rotor gives of its nominal thrust (a mismatched motor, a sagging battery); the
    onboard loops do not know either. ``attitude_bias`` is the error of the flight controller's
    attitude estimate (``R_estimate = R_world_body @ attitude_bias``), which its loops follow.

    The state is held in Python floats and the loops are written out in scalars: they run at
    the physics rate, where numpy's per-call overhead on 3-vectors costs more than the
    arithmetic. The properties give and take numpy arrays.
    """

    takes_plate_forces = True  # ``plate`` acts on it (a plant integrated elsewhere: False)

    def __init__(
        self,
        params: QuadrotorParams | None = None,
        gains: OnboardGains | None = None,
        p_m: Array | None = None,
        ceiling_z_m: float | None = None,
        ceiling_half_size_m: float | None = None,
    ) -> None:
        self.params = params or QuadrotorParams()
        self.gains = gains or OnboardGains()
        self.ceiling_z_m = ceiling_z_m
        # the ceiling is a square of this half size about x = y = 0 (the plate); None: endless
        self.ceiling_half_size_m = ceiling_half_size_m
        mix = mixer(self.params)
        self._mix_rows: list[list[float]] = mix.tolist()
        self._unmix_rows: list[list[float]] = np.linalg.inv(mix).tolist()
        self._p: Vec3 = vec3(np.zeros(3) if p_m is None else p_m)
        self._v: Vec3 = (0.0, 0.0, 0.0)
        self._R: Mat3 = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))
        self._w: Vec3 = (0.0, 0.0, 0.0)
        hover = math.sqrt(self.params.weight_n / 4 / self.params.k_thrust)
        self._rotor: tuple[float, float, float, float] = (hover, hover, hover, hover)
        self.wind_mps: Vec3 = (0.0, 0.0, 0.0)
        self.thrust_scale: tuple[float, float, float, float] = (1.0, 1.0, 1.0, 1.0)
        self._bias: Mat3 | None = None
        # the flight controller's own estimator (None: the truth, ``attitude_bias`` and the
        # velocity estimate ``fly`` is given)
        self.estimator: OnboardEstimate | None = None
        # the onboard velocity integral, m/s^2 (the vertical one as the trim of a hover: none
        # where the vehicle holds its weight with it)
        self._vi: Vec3 = (0.0, 0.0, 0.0)
        # the attitude error about body x and y (rad) at the last step, and its integral
        self._attitude_error: tuple[float, float] = (0.0, 0.0)
        self._attitude_i: tuple[float, float] = (0.0, 0.0)
        # a full-state or attitude setpoint the vehicle holds (None: it flies the velocity
        # ``fly`` is given), and its position estimate at this step
        self.hold: Hold | None = None
        self._mode = setpoint_mode(None)  # the kind of setpoint flown at the last step
        # the height error (m) the position loop saw at the last step, and its integral
        self._height_error = 0.0
        self._height_i = 0.0
        self._p_estimate: Vec3 = (0.0, 0.0, 0.0)
        # the plate's forces (its face, friction and magnet) where it can reach (None: free
        # flight; the contact is then only watched, ``perchpose.sim.contact.PlateContact``)
        self.plate: PlateWrench | None = None
        self._k_xy = self.gains.k_velocity  # the horizontal velocity gain (a parameter), 1/s
        self._f_body: Vec3 = (0.0, 0.0, GRAVITY_MPS2)  # the accelerometer, low-passed
        a = self.params.arm_m
        self._hubs = ((a, a), (a, -a), (-a, -a), (-a, a))
        self._spin = (1.0, -1.0, 1.0, -1.0)

    @staticmethod
    def hovering(
        params: QuadrotorParams, p_m: Array, yaw_rad: float, gains: OnboardGains | None = None
    ) -> Quadrotor:
        """A vehicle hovering at ``p_m`` with heading ``yaw_rad``."""
        q = Quadrotor(params, gains, np.asarray(p_m, np.float64))
        q.R_world_body = rot_z(yaw_rad)
        return q

    @property
    def p_m(self) -> Array:
        """Position, world frame, metres."""
        return np.array(self._p)

    @p_m.setter
    def p_m(self, value: Array) -> None:
        self._p = vec3(value)

    @property
    def v_mps(self) -> Array:
        """Velocity, world frame, m/s."""
        return np.array(self._v)

    @v_mps.setter
    def v_mps(self, value: Array) -> None:
        self._v = vec3(value)

    @property
    def R_world_body(self) -> Array:
        """Attitude: body axes as columns in the world frame."""
        return np.array(self._R)

    @R_world_body.setter
    def R_world_body(self, value: Array) -> None:
        self._R = mat3(value)

    @property
    def omega_rad_s(self) -> Array:
        """Body rates, body frame, rad/s."""
        return np.array(self._w)

    @omega_rad_s.setter
    def omega_rad_s(self, value: Array) -> None:
        self._w = vec3(value)

    @property
    def rotor_speed_rad_s(self) -> Array:
        """Speed of each rotor, rad/s."""
        return np.array(self._rotor)

    @rotor_speed_rad_s.setter
    def rotor_speed_rad_s(self, value: Array) -> None:
        w = [float(c) for c in np.asarray(value, np.float64).reshape(4)]
        self._rotor = (w[0], w[1], w[2], w[3])

    @property
    def thrust_n(self) -> Array:
        """Thrust of each rotor, newtons (without the ceiling effect)."""
        k = self.params.k_thrust
        return np.array(
            [k * s * w * w for s, w in zip(self.thrust_scale, self._rotor, strict=True)]
        )

    @property
    def attitude_bias(self) -> Array:
        """The attitude estimate's error, a rotation in the body frame."""
        return np.eye(3) if self._bias is None else np.array(self._bias).reshape(3, 3)

    @attitude_bias.setter
    def attitude_bias(self, value: Array) -> None:
        self._bias = mat3(value)

    @property
    def R_estimate(self) -> Array:
        """The flight controller's attitude estimate: its ``estimator``'s, or
        ``R_world_body @ attitude_bias``."""
        return np.array(self._attitude_estimate())

    def _attitude_estimate(self) -> Mat3:
        if self.estimator is not None:
            return self.estimator.attitude
        return self._R if self._bias is None else _product(self._R, self._bias)

    @property
    def yaw_rad(self) -> float:
        """Heading of the body x axis."""
        return math.atan2(self._R[1][0], self._R[0][0])

    def ceiling_factor(self, rotor: int | None = None) -> float:
        """Thrust gain near a ceiling: 1 / (1 - (r / 4d)^2), capped at 1.5, with ``d`` the
        distance from the ceiling to the rotor's hub in the rotor plane (``rotor`` None: to
        the centre of the rotor plane), for the share of the rotor's disc under the ceiling
        (``_under_ceiling``)."""
        if self.ceiling_z_m is None:
            return 1.0
        hx, hy = (0.0, 0.0) if rotor is None else self._hubs[rotor]
        x, y, z = self.point_in_world((hx, hy, self.params.rotor_plane_m))
        gain = _ceiling_gain(self.ceiling_z_m - z, self.params.prop_radius_m)
        return 1.0 + (gain - 1.0) * self._under_ceiling(x, y)

    def _ceiling_gains(self, R: Mat3) -> tuple[float, ...]:
        """``ceiling_factor`` of each rotor for the attitude ``R``, written out in scalars (it
        runs at the physics rate)."""
        ceiling, half = self.ceiling_z_m, self.ceiling_half_size_m
        if ceiling is None:
            return (1.0, 1.0, 1.0, 1.0)
        r, plane = self.params.prop_radius_m, self.params.rotor_plane_m
        px, py, pz = self._p
        cx, cy, cz = px + R[0][2] * plane, py + R[1][2] * plane, pz + R[2][2] * plane
        gains = []
        for hx, hy in self._hubs:
            gain = _ceiling_gain(ceiling - (cz + R[2][0] * hx + R[2][1] * hy), r)
            if half is not None:
                x = abs(cx + R[0][0] * hx + R[0][1] * hy)
                y = abs(cy + R[1][0] * hx + R[1][1] * hy)
                if x > half - r or y > half - r:  # the disc reaches past the plate's edge
                    share_x = min(1.0, max(0.0, (half - x + r) / (2.0 * r)))
                    share_y = min(1.0, max(0.0, (half - y + r) / (2.0 * r)))
                    gain = 1.0 + (gain - 1.0) * share_x * share_y
            gains.append(gain)
        return tuple(gains)

    def _under_ceiling(self, x_m: float, y_m: float) -> float:
        """The share of a rotor's disc centred at (``x_m``, ``y_m``) that the ceiling covers,
        taken as the product of the covered shares of the disc's square along x and y (1 for
        an endless ceiling): the ceiling effect acts only under the plate."""
        half = self.ceiling_half_size_m
        if half is None:
            return 1.0
        r = self.params.prop_radius_m
        share_x = min(1.0, max(0.0, (half - abs(x_m) + r) / (2.0 * r)))
        share_y = min(1.0, max(0.0, (half - abs(y_m) + r) / (2.0 * r)))
        return share_x * share_y

    def point_in_world(self, p_body_m: Vec3) -> Vec3:
        """A point fixed to the body (body frame, metres) in the world frame."""
        (r00, r01, r02), (r10, r11, r12), (r20, r21, r22) = self._R
        x, y, z = p_body_m
        px, py, pz = self._p
        return (
            px + r00 * x + r01 * y + r02 * z,
            py + r10 * x + r11 * y + r12 * z,
            pz + r20 * x + r21 * y + r22 * z,
        )

    def motor_commands(self, v_sp_mps: Array, yaw_rate_sp: float, v_estimate_mps: Array) -> Array:
        """The onboard loops: world velocity setpoint and yaw rate -> motor thrust commands."""
        return np.array(
            self._motor_commands(vec3(v_sp_mps), float(yaw_rate_sp), vec3(v_estimate_mps))
        )

    def step(self, dt_s: float, motor_cmd_n: Array) -> None:
        """Advance ``dt_s`` seconds (semi-implicit Euler) with these thrust commands (N)."""
        c = [float(x) for x in np.asarray(motor_cmd_n, np.float64).reshape(4)]
        self._advance(dt_s, (c[0], c[1], c[2], c[3]))

    @property
    def specific_force_body_mps2(self) -> Array:
        """What an accelerometer at the centre of mass reads, body frame, m/s^2: the
        acceleration less gravity (at rest, +g along body z), low-passed at
        ``ACCEL_CUTOFF_HZ`` as the Crazyflie firmware filters its IMU's. Along body x and y
        it is the aerodynamic push over the mass (thrust has no part there)."""
        return np.array(self._f_body)

    def _advance(self, dt_s: float, cmd: tuple[float, float, float, float]) -> None:
        """One step of the dynamics, and the accelerometer's reading of it."""
        v0 = self._v
        self._step(dt_s, cmd)
        v1, R = self._v, self._R
        ax = (v1[0] - v0[0]) / dt_s
        ay = (v1[1] - v0[1]) / dt_s
        az = (v1[2] - v0[2]) / dt_s + GRAVITY_MPS2
        alpha = 1.0 - math.exp(-2.0 * math.pi * ACCEL_CUTOFF_HZ * dt_s)
        fx, fy, fz = self._f_body
        self._f_body = (
            fx + alpha * (R[0][0] * ax + R[1][0] * ay + R[2][0] * az - fx),
            fy + alpha * (R[0][1] * ax + R[1][1] * ay + R[2][1] * az - fy),
            fz + alpha * (R[0][2] * ax + R[1][2] * ay + R[2][2] * az - fz),
        )

    def fly(
        self,
        dt_s: float,
        n_steps: int,
        v_sp_mps: Array,
        yaw_rate_sp: float,
        v_estimate_mps: Array,
        touched: Callable[[Quadrotor], bool] | None = None,
    ) -> int | None:
        """``n_steps`` steps of the onboard loops and the dynamics with the same setpoint and
        velocity estimate (with an ``estimator``: its velocity, step by step); while ``hold``
        is set, the setpoint is its position and yaw (``_position_loop``), or its lean and
        height, and the velocity and yaw rate given are not flown. Stops after the
        step on which ``touched`` says the vehicle touched something (``perchpose.sim.contact``)
        and returns that step's index; otherwise returns None."""
        v_sp, v_est, yaw_rate = vec3(v_sp_mps), vec3(v_estimate_mps), float(yaw_rate_sp)
        estimator, hold = self.estimator, self.hold
        mode = setpoint_mode(hold)
        if mode != self._mode:
            self._mode = mode
            self._reset_integrals()
        for i in range(n_steps):
            if estimator is not None:
                v_est = estimator.velocity
            if hold is not None:
                self._p_estimate = (
                    estimator.position
                    if estimator is not None
                    else _carried(hold.p_estimate_m, v_est, i * dt_s)
                )
                v_sp, yaw_rate = self._position_loop(hold, v_est)
            self._integrate_errors(dt_s, v_sp, v_est)
            self._advance(dt_s, self._motor_commands(v_sp, yaw_rate, v_est))
            if estimator is not None:
                estimator.advance(dt_s, self)
            if touched is not None and touched(self):
                return i
        return None

    def _position_loop(self, hold: Hold, v_est: Vec3) -> tuple[Vec3, float]:
        """The velocity and yaw rate that hold ``hold``'s position and yaw from the position
        estimate: the firmware's PID position loop (proportional, capped; the height with its
        integral too). An attitude hold has its height held so, and its lean and yaw rate
        flown as they are (its horizontal velocity error is none: the velocity loop's integral
        stays as it is)."""
        g = self.gains
        top = g.max_position_speed_mps
        z_m = hold.z_m if isinstance(hold, AttitudeHold) else hold.p_m[2]
        self._height_error = z_m - self._p_estimate[2]
        ez = self._height_error + g.k_height_i / g.k_position * self._height_i
        if isinstance(hold, AttitudeHold):
            climb = max(-top, min(top, g.k_position * ez))
            return (v_est[0], v_est[1], climb), hold.yaw_rate_rad_s
        ex, ey = (s - e for s, e in zip(hold.p_m[:2], self._p_estimate[:2], strict=True))
        v_sp = (
            max(-top, min(top, g.k_position * ex)),
            max(-top, min(top, g.k_position * ey)),
            max(-top, min(top, g.k_position * ez)),
        )
        R = self._attitude_estimate()
        yaw_error = math.remainder(hold.yaw_rad - math.atan2(R[1][0], R[0][0]), math.tau)
        return v_sp, g.k_yaw * yaw_error

    def set_velocity_gain(self, gain_per_s: float | None) -> bool:
        """Set the onboard loops' horizontal velocity gain, 1/s, as a pilot sets the flight
        controller's parameter (None: the gains' own back). True: it took."""
        self._k_xy = self.gains.k_velocity if gain_per_s is None else float(gain_per_s)
        return True

    def settle(self) -> None:
        """Bring the onboard loops to a steady hover where the vehicle is (the model's loops
        start settled: nothing to do)."""

    @property
    def hubs_m(self) -> tuple[tuple[float, float], ...]:
        """The rotor hubs' (x, y) on the body, metres."""
        return self._hubs

    def _reset_integrals(self) -> None:
        """The onboard loops' integrals zeroed, as on a change of setpoint mode: the vertical
        one then holds nothing of the weight beyond ``thrust_base_n``."""
        g, m = self.gains, self.params.mass_kg
        self._vi = (0.0, 0.0, g.thrust_base_n / m - GRAVITY_MPS2)
        self._attitude_i = (0.0, 0.0)
        self._height_i = 0.0

    def _integrate_errors(self, dt_s: float, v_sp: Vec3, v_est: Vec3) -> None:
        """The onboard loops' integrals over ``dt_s``: the velocity error's, and the height's
        and the attitude's errors as the last step left them (the height's only where the
        setpoint holds a height)."""
        g = self.gains
        k_xy, k_z = g.k_velocity_i
        top = g.max_velocity_i_mps2
        ix, iy, iz = self._vi
        self._vi = (
            min(top, max(-top, ix + dt_s * k_xy * (v_sp[0] - v_est[0]))),
            min(top, max(-top, iy + dt_s * k_xy * (v_sp[1] - v_est[1]))),
            min(top, max(-top, iz + dt_s * k_z * (v_sp[2] - v_est[2]))),
        )
        if self._mode in ("height", "position"):
            self._height_i += dt_s * self._height_error
        if g.k_attitude_i > 0.0:
            cap = g.attitude_i_limit
            (ax, ay), (ex, ey) = self._attitude_i, self._attitude_error
            self._attitude_i = (
                min(cap, max(-cap, ax + dt_s * ex)),
                min(cap, max(-cap, ay + dt_s * ey)),
            )

    def _motor_commands(
        self, v_sp: Vec3, yaw_rate_sp: float, v_est: Vec3
    ) -> tuple[float, float, float, float]:
        p, g = self.params, self.gains
        m = p.mass_kg
        ix, iy, iz = self._vi
        fx = m * (self._k_xy * (v_sp[0] - v_est[0]) + ix)
        fy = m * (self._k_xy * (v_sp[1] - v_est[1]) + iy)
        fz = m * (g.k_velocity_z * (v_sp[2] - v_est[2]) + iz + GRAVITY_MPS2)
        (r00, r01, r02), (r10, r11, r12), (r20, r21, r22) = self._attitude_estimate()
        yaw = math.atan2(r10, r00)
        hold = self.hold
        if isinstance(hold, AttitudeHold):
            if hold.thrust_fraction is not None:
                fz = hold.thrust_fraction * g.thrust_base_n
            tx, ty = leaned(hold.roll_rad, hold.pitch_rad, yaw)
            fx, fy = fz * tx, fz * ty
        # limit the tilt of the thrust vector
        horizontal = math.hypot(fx, fy)
        max_h = max(fz, 0.1 * p.weight_n) * math.tan(g.max_tilt_rad)
        if horizontal > max_h:
            fx *= max_h / horizontal
            fy *= max_h / horizontal
        norm = math.sqrt(fx * fx + fy * fy + fz * fz)
        zx, zy, zz = fx / norm, fy / norm, fz / norm
        cx, cy = math.cos(yaw), math.sin(yaw)
        # y_b = z_b x x_c, normalised; x_b = y_b x z_b: the columns of R_des
        yx, yy, yz = -zz * cy, zz * cx, zx * cy - zy * cx
        n = math.sqrt(yx * yx + yy * yy + yz * yz)
        yx, yy, yz = yx / n, yy / n, yz / n
        xx, xy, xz = yy * zz - yz * zy, yz * zx - yx * zz, yx * zy - yy * zx
        thrust = fx * r02 + fy * r12 + fz * r22 if g.tilt_compensated else fz
        # attitude error: vee of the skew part of R_des^T R, body frame
        a21 = zx * r01 + zy * r11 + zz * r21
        a12 = yx * r02 + yy * r12 + yz * r22
        a02 = xx * r02 + xy * r12 + xz * r22
        a20 = zx * r00 + zy * r10 + zz * r20
        e_x = 0.5 * (a21 - a12)
        e_y = 0.5 * (a02 - a20)
        self._attitude_error = (e_x, e_y)
        lim = g.max_rate_rad_s
        ai_x, ai_y = self._attitude_i
        rate_x = min(lim, max(-lim, -g.k_attitude * e_x - g.k_attitude_i * ai_x))
        rate_y = min(lim, max(-lim, -g.k_attitude * e_y - g.k_attitude_i * ai_y))
        ix, iy, iz = p.inertia_kg_m2
        wx, wy, wz = self._w
        hx, hy, hz = ix * wx, iy * wy, iz * wz  # angular momentum
        tau_x = g.k_rate * ix / 1.66e-5 * (rate_x - wx) + (wy * hz - wz * hy)
        tau_y = g.k_rate * iy / 1.66e-5 * (rate_y - wy) + (wz * hx - wx * hz)
        tau_z = g.k_yaw_rate * iz / 1.66e-5 * (yaw_rate_sp - wz) + (wx * hy - wy * hx)
        return _mixed(self._unmix_rows, (max(thrust, 0.0), tau_x, tau_y, tau_z), p.max_thrust_n)

    def _step(self, dt_s: float, cmd: tuple[float, float, float, float]) -> None:
        p = self.params
        k_thrust, top = p.k_thrust, p.max_rotor_speed_rad_s
        alpha = min(1.0, dt_s / p.motor_tau_s)
        rotor = [
            w + alpha * (min(top, math.sqrt(max(0.0, f) / k_thrust)) - w)
            for w, f in zip(self._rotor, cmd, strict=True)
        ]
        self._rotor = (rotor[0], rotor[1], rotor[2], rotor[3])
        R = self._R
        vx, vy, vz = self._v
        wind = self.wind_mps
        # the air past the body, body frame
        dx, dy, dz = vx - wind[0], vy - wind[1], vz - wind[2]
        ax = R[0][0] * dx + R[1][0] * dy + R[2][0] * dz
        ay = R[0][1] * dx + R[1][1] * dy + R[2][1] * dz
        az = R[0][2] * dx + R[1][2] * dy + R[2][2] * dz
        wx, wy, wz = self._w
        kd, kz = p.rotor_drag_kg_per_rad, p.inflow_drag_kg_per_rad
        fx = fy = fz = 0.0
        tau_x = tau_y = tau_z = 0.0
        gains = self._ceiling_gains(R)
        for (hx, hy), spin, scale, w, gain in zip(
            self._hubs, self._spin, self.thrust_scale, rotor, gains, strict=True
        ):
            thrust = gain * scale * k_thrust * w * w
            # H-force from the air at this hub (body velocity plus omega x r)
            h_x = -w * kd * (ax - wz * hy)
            h_y = -w * kd * (ay + wz * hx)
            h_z = -w * kz * (az + wx * hy - wy * hx)
            f_z = thrust + h_z
            fx += h_x
            fy += h_y
            fz += f_z
            tau_x += hy * f_z
            tau_y -= hx * f_z
            tau_z += hx * h_y - hy * h_x + spin * p.yaw_moment_m * thrust
        c_xy, c_z = p.body_drag_n_per_mps2
        speed = math.sqrt(ax * ax + ay * ay + az * az)
        fx -= speed * c_xy * ax
        fy -= speed * c_xy * ay
        fz -= speed * c_z * az
        plate = self.plate
        n = 1 if plate is None else plate.substeps(self._p, R)
        h = dt_s / n
        for _ in range(n):
            self._integrate(h, (fx, fy, fz), (tau_x, tau_y, tau_z), plate)

    def _integrate(
        self, dt_s: float, f_body: Vec3, tau_body: Vec3, plate: PlateWrench | None
    ) -> None:
        """Semi-implicit Euler through ``dt_s`` with the rotors' and the air's force and
        torque (body frame) and what the plate adds (world force, body torque)."""
        p = self.params
        R = self._R
        fx, fy, fz = f_body
        tau_x, tau_y, tau_z = tau_body
        vx, vy, vz = self._v
        wx, wy, wz = self._w
        ex = ey = ez = 0.0
        if plate is not None:
            extra = plate.wrench(self._p, self._v, R, self._w)
            if extra is not None:
                (ex, ey, ez), (tx, ty, tz) = extra
                tau_x, tau_y, tau_z = tau_x + tx, tau_y + ty, tau_z + tz
        k = dt_s / p.mass_kg
        vx += k * (R[0][0] * fx + R[0][1] * fy + R[0][2] * fz + ex)
        vy += k * (R[1][0] * fx + R[1][1] * fy + R[1][2] * fz + ey)
        vz += k * (R[2][0] * fx + R[2][1] * fy + R[2][2] * fz - p.weight_n + ez)
        px, py, pz = self._p
        self._p = (px + dt_s * vx, py + dt_s * vy, pz + dt_s * vz)
        self._v = (vx, vy, vz)
        ix, iy, iz = p.inertia_kg_m2
        hx_, hy_, hz_ = ix * wx, iy * wy, iz * wz
        wx, wy, wz = (
            wx + dt_s * (tau_x - (wy * hz_ - wz * hy_)) / ix,
            wy + dt_s * (tau_y - (wz * hx_ - wx * hz_)) / iy,
            wz + dt_s * (tau_z - (wx * hy_ - wy * hx_)) / iz,
        )
        self._w = (wx, wy, wz)
        angle = dt_s * math.sqrt(wx * wx + wy * wy + wz * wz)
        if angle > 0:
            self._R = _rotated(R, (dt_s * wx / angle, dt_s * wy / angle, dt_s * wz / angle), angle)


def _carried(p_m: Vec3, v_mps: Vec3, t_s: float) -> Vec3:
    """A position moved ``t_s`` along a velocity."""
    return (p_m[0] + v_mps[0] * t_s, p_m[1] + v_mps[1] * t_s, p_m[2] + v_mps[2] * t_s)


def _ceiling_gain(distance_m: float, prop_radius_m: float) -> float:
    """The ceiling effect's thrust gain for a rotor ``distance_m`` below the ceiling
    (Cheeseman and Bennett's image-rotor model, 1 / (1 - (r / 4d)^2)), capped at 1.5."""
    ratio = prop_radius_m / (4.0 * max(distance_m, 1e-3))
    return min(1.5, 1.0 / max(1e-3, 1.0 - ratio * ratio))


def _mixed(
    rows: list[list[float]], wrench: tuple[float, float, float, float], top: float
) -> tuple[float, float, float, float]:
    """Motor thrusts ``rows @ wrench``, each limited to [0, top]."""
    t, x, y, z = wrench
    f = [min(top, max(0.0, r[0] * t + r[1] * x + r[2] * y + r[3] * z)) for r in rows]
    return (f[0], f[1], f[2], f[3])


def _product(A: Mat3, B: Mat3) -> Mat3:
    """A @ B for 3x3 tuples."""
    rows = [
        (
            a[0] * B[0][0] + a[1] * B[1][0] + a[2] * B[2][0],
            a[0] * B[0][1] + a[1] * B[1][1] + a[2] * B[2][1],
            a[0] * B[0][2] + a[1] * B[1][2] + a[2] * B[2][2],
        )
        for a in A
    ]
    return (rows[0], rows[1], rows[2])


def vec3(value: Array | Sequence[float]) -> Vec3:
    """A 3-vector as a tuple of Python floats (the form the scalar loops take)."""
    x, y, z = (float(c) for c in np.asarray(value, np.float64).reshape(3))
    return (x, y, z)


def mat3(value: Array) -> Mat3:
    """A 3x3 matrix as rows of Python floats, the form the loops run on."""
    rows = np.asarray(value, np.float64).reshape(3, 3).tolist()
    return (vec3(rows[0]), vec3(rows[1]), vec3(rows[2]))


def _rotated(R: Mat3, axis: Vec3, angle: float) -> Mat3:
    """R @ exp([axis * angle]x) (Rodrigues), then Gram-Schmidt on the columns."""
    ax, ay, az = axis
    sa, ca = math.sin(angle), 1.0 - math.cos(angle)
    # the first two columns of dR; the third column of the result is the cross product
    d00, d10, d20 = 1 - ca * (ay * ay + az * az), sa * az + ca * ax * ay, -sa * ay + ca * ax * az
    d01, d11, d21 = -sa * az + ca * ax * ay, 1 - ca * (ax * ax + az * az), sa * ax + ca * ay * az
    (r00, r01, r02), (r10, r11, r12), (r20, r21, r22) = R
    m00 = r00 * d00 + r01 * d10 + r02 * d20
    m10 = r10 * d00 + r11 * d10 + r12 * d20
    m20 = r20 * d00 + r21 * d10 + r22 * d20
    m01 = r00 * d01 + r01 * d11 + r02 * d21
    m11 = r10 * d01 + r11 * d11 + r12 * d21
    m21 = r20 * d01 + r21 * d11 + r22 * d21
    n0 = math.sqrt(m00 * m00 + m10 * m10 + m20 * m20)
    c00, c01, c02 = m00 / n0, m10 / n0, m20 / n0
    d = c00 * m01 + c01 * m11 + c02 * m21
    c10, c11, c12 = m01 - d * c00, m11 - d * c01, m21 - d * c02
    n1 = math.sqrt(c10 * c10 + c11 * c11 + c12 * c12)
    c10, c11, c12 = c10 / n1, c11 / n1, c12 / n1
    c20 = c01 * c12 - c02 * c11
    c21 = c02 * c10 - c00 * c12
    c22 = c00 * c11 - c01 * c10
    return ((c00, c10, c20), (c01, c11, c21), (c02, c12, c22))

"""A small quadrotor: rigid body, four motors with first-order response, and the onboard
attitude and velocity loops of a flight controller such as the Crazyflie's.

World frame: x, y horizontal, z up (metres). Body frame: x forward, y left, z up. Motors in
an X: front-left, front-right, back-right, back-left. Plain numpy.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from perchpose.errors import PerchposeError
from perchpose.geometry import rot_z

Array = NDArray[np.float64]
GRAVITY_MPS2 = 9.81


class VehicleConfigError(PerchposeError):
    """Physically impossible or unstable vehicle or controller settings."""


@dataclass(frozen=True)
class QuadrotorParams:
    """Defaults: a Crazyflie 2.1 carrying an FPV camera and a magnet (39 g, as in the paper).

    inertia_kg_m2 : diagonal of the inertia tensor. arm_m : motor offset along body x and y.
    max_thrust_n : per motor. motor_tau_s : first-order motor time constant.
    yaw_moment_m : reaction torque per newton of thrust. drag_n_s_per_m : linear drag.
    prop_radius_m : for the ceiling effect.
    """

    mass_kg: float = 0.039
    inertia_kg_m2: tuple[float, float, float] = (1.66e-5, 1.66e-5, 2.93e-5)
    arm_m: float = 0.0325
    max_thrust_n: float = 0.16
    motor_tau_s: float = 0.03
    yaw_moment_m: float = 0.006
    drag_n_s_per_m: float = 0.01
    prop_radius_m: float = 0.0235

    def __post_init__(self) -> None:
        if not self.mass_kg > 0:
            raise VehicleConfigError(f"mass must be positive, got {self.mass_kg} kg")
        if not all(i > 0 for i in self.inertia_kg_m2):
            raise VehicleConfigError("every inertia must be positive")
        if not (self.arm_m > 0 and self.motor_tau_s > 0 and self.max_thrust_n > 0):
            raise VehicleConfigError("arm, motor time constant and max thrust must be positive")
        ratio = 4 * self.max_thrust_n / (self.mass_kg * GRAVITY_MPS2)
        if ratio < 1.2:
            raise VehicleConfigError(
                f"thrust-to-weight {ratio:.2f} is too low to fly (need at least 1.2)"
            )

    @property
    def weight_n(self) -> float:
        """Weight in newtons."""
        return self.mass_kg * GRAVITY_MPS2


@dataclass(frozen=True)
class OnboardGains:
    """The flight controller's loops: velocity -> attitude -> rate -> torque."""

    k_velocity: float = 3.0  # 1/s
    max_tilt_rad: float = math.radians(20.0)
    k_attitude: float = 8.0  # 1/s
    k_rate: float = 0.004  # N m / (rad/s) per unit inertia scale
    k_yaw_rate: float = 0.0008
    max_rate_rad_s: float = 6.0


def mixer(params: QuadrotorParams) -> Array:
    """(4, 4) matrix from motor thrusts to [thrust, torque_x, torque_y, torque_z]."""
    a, k = params.arm_m, params.yaw_moment_m
    # motors: front-left (+a, +a), front-right (+a, -a), back-right (-a, -a), back-left (-a, +a)
    # spin: FL and BR clockwise seen from above (negative yaw torque), FR and BL anticlockwise
    return np.array(
        [
            [1.0, 1.0, 1.0, 1.0],
            [a, -a, -a, a],  # roll torque = sum(y_i f_i)
            [-a, -a, a, a],  # pitch torque = -sum(x_i f_i)
            [-k, k, -k, k],
        ]
    )


Vec3 = tuple[float, float, float]
Mat3 = tuple[Vec3, Vec3, Vec3]


class Quadrotor:
    """The vehicle's state and its integration. ``p_m``, ``v_mps`` in the world frame;
    ``R_world_body``; ``omega_rad_s`` in the body frame; ``thrust_n`` per motor.

    The state is held in Python floats and the loops are written out in scalars: they run at
    the physics rate, where numpy's per-call overhead on 3-vectors costs more than the
    arithmetic. The properties give and take numpy arrays.
    """

    def __init__(
        self,
        params: QuadrotorParams | None = None,
        gains: OnboardGains | None = None,
        p_m: Array | None = None,
        ceiling_z_m: float | None = None,
    ) -> None:
        self.params = params or QuadrotorParams()
        self.gains = gains or OnboardGains()
        self.ceiling_z_m = ceiling_z_m
        mix = mixer(self.params)
        self._mix_rows: list[list[float]] = mix.tolist()
        self._unmix_rows: list[list[float]] = np.linalg.inv(mix).tolist()
        self._p: Vec3 = _vec3(np.zeros(3) if p_m is None else p_m)
        self._v: Vec3 = (0.0, 0.0, 0.0)
        self._R: Mat3 = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))
        self._w: Vec3 = (0.0, 0.0, 0.0)
        hover = self.params.weight_n / 4
        self._f: tuple[float, float, float, float] = (hover, hover, hover, hover)  # in hover

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
        self._p = _vec3(value)

    @property
    def v_mps(self) -> Array:
        """Velocity, world frame, m/s."""
        return np.array(self._v)

    @v_mps.setter
    def v_mps(self, value: Array) -> None:
        self._v = _vec3(value)

    @property
    def R_world_body(self) -> Array:
        """Attitude: body axes as columns in the world frame."""
        return np.array(self._R)

    @R_world_body.setter
    def R_world_body(self, value: Array) -> None:
        rows = np.asarray(value, np.float64).reshape(3, 3).tolist()
        self._R = (_vec3(rows[0]), _vec3(rows[1]), _vec3(rows[2]))

    @property
    def omega_rad_s(self) -> Array:
        """Body rates, body frame, rad/s."""
        return np.array(self._w)

    @omega_rad_s.setter
    def omega_rad_s(self, value: Array) -> None:
        self._w = _vec3(value)

    @property
    def thrust_n(self) -> Array:
        """Thrust of each motor, newtons."""
        return np.array(self._f)

    @thrust_n.setter
    def thrust_n(self, value: Array) -> None:
        f = [float(c) for c in np.asarray(value, np.float64).reshape(4)]
        self._f = (f[0], f[1], f[2], f[3])

    @property
    def yaw_rad(self) -> float:
        """Heading of the body x axis."""
        return math.atan2(self._R[1][0], self._R[0][0])

    def ceiling_factor(self) -> float:
        """Thrust gain near a ceiling: 1 / (1 - (r / 4d)^2), capped at 1.5."""
        if self.ceiling_z_m is None:
            return 1.0
        d = max(self.ceiling_z_m - self._p[2], 1e-3)
        ratio = self.params.prop_radius_m / (4.0 * d)
        return min(1.5, 1.0 / max(1e-3, 1.0 - ratio * ratio))

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
            self._motor_commands(_vec3(v_sp_mps), float(yaw_rate_sp), _vec3(v_estimate_mps))
        )

    def step(self, dt_s: float, motor_cmd_n: Array, force_world_n: Array | None = None) -> None:
        """Advance ``dt_s`` seconds (semi-implicit Euler)."""
        c = [float(x) for x in np.asarray(motor_cmd_n, np.float64).reshape(4)]
        force = (0.0, 0.0, 0.0) if force_world_n is None else _vec3(force_world_n)
        self._step(dt_s, (c[0], c[1], c[2], c[3]), force)

    def fly(
        self,
        dt_s: float,
        n_steps: int,
        v_sp_mps: Array,
        yaw_rate_sp: float,
        v_estimate_mps: Array,
        forces_world_n: Array | None = None,
        stop_z_m: float | None = None,
        p_body_point_m: Array | None = None,
    ) -> int | None:
        """``n_steps`` steps of the onboard loops and the dynamics with the same setpoint and
        velocity estimate; ``forces_world_n`` (n_steps, 3) per step. With ``stop_z_m``, stops
        after the step on which the body point ``p_body_point_m`` reaches that height and
        returns that step's index; otherwise returns None."""
        v_sp, v_est, yaw_rate = _vec3(v_sp_mps), _vec3(v_estimate_mps), float(yaw_rate_sp)
        forces = None if forces_world_n is None else np.asarray(forces_world_n).tolist()
        point = (0.0, 0.0, 0.0) if p_body_point_m is None else _vec3(p_body_point_m)
        zero = (0.0, 0.0, 0.0)
        for i in range(n_steps):
            cmd = self._motor_commands(v_sp, yaw_rate, v_est)
            self._step(dt_s, cmd, zero if forces is None else forces[i])
            if stop_z_m is not None and self.point_in_world(point)[2] >= stop_z_m:
                return i
        return None

    def _motor_commands(
        self, v_sp: Vec3, yaw_rate_sp: float, v_est: Vec3
    ) -> tuple[float, float, float, float]:
        p, g = self.params, self.gains
        m = p.mass_kg
        fx = m * g.k_velocity * (v_sp[0] - v_est[0])
        fy = m * g.k_velocity * (v_sp[1] - v_est[1])
        fz = m * (g.k_velocity * (v_sp[2] - v_est[2]) + GRAVITY_MPS2)
        # limit the tilt of the thrust vector
        horizontal = math.hypot(fx, fy)
        max_h = max(fz, 0.1 * p.weight_n) * math.tan(g.max_tilt_rad)
        if horizontal > max_h:
            fx *= max_h / horizontal
            fy *= max_h / horizontal
        norm = math.sqrt(fx * fx + fy * fy + fz * fz)
        zx, zy, zz = fx / norm, fy / norm, fz / norm
        (r00, r01, r02), (r10, r11, r12), (r20, r21, r22) = self._R
        yaw = math.atan2(r10, r00)
        cx, cy = math.cos(yaw), math.sin(yaw)
        # y_b = z_b x x_c, normalised; x_b = y_b x z_b: the columns of R_des
        yx, yy, yz = -zz * cy, zz * cx, zx * cy - zy * cx
        n = math.sqrt(yx * yx + yy * yy + yz * yz)
        yx, yy, yz = yx / n, yy / n, yz / n
        xx, xy, xz = yy * zz - yz * zy, yz * zx - yx * zz, yx * zy - yy * zx
        thrust = fx * r02 + fy * r12 + fz * r22
        # attitude error: vee of the skew part of R_des^T R, body frame
        a21 = zx * r01 + zy * r11 + zz * r21
        a12 = yx * r02 + yy * r12 + yz * r22
        a02 = xx * r02 + xy * r12 + xz * r22
        a20 = zx * r00 + zy * r10 + zz * r20
        e_x = 0.5 * (a21 - a12)
        e_y = 0.5 * (a02 - a20)
        lim = g.max_rate_rad_s
        rate_x = min(lim, max(-lim, -g.k_attitude * e_x))
        rate_y = min(lim, max(-lim, -g.k_attitude * e_y))
        ix, iy, iz = p.inertia_kg_m2
        wx, wy, wz = self._w
        hx, hy, hz = ix * wx, iy * wy, iz * wz  # angular momentum
        tau_x = g.k_rate * ix / 1.66e-5 * (rate_x - wx) + (wy * hz - wz * hy)
        tau_y = g.k_rate * iy / 1.66e-5 * (rate_y - wy) + (wz * hx - wx * hz)
        tau_z = g.k_yaw_rate * iz / 1.66e-5 * (yaw_rate_sp - wz) + (wx * hy - wy * hx)
        return _mixed(self._unmix_rows, (max(thrust, 0.0), tau_x, tau_y, tau_z), p.max_thrust_n)

    def _step(
        self, dt_s: float, cmd: tuple[float, float, float, float], force: Sequence[float]
    ) -> None:
        p = self.params
        alpha = min(1.0, dt_s / p.motor_tau_s)
        f0, f1, f2, f3 = self._f
        f0 += alpha * (cmd[0] - f0)
        f1 += alpha * (cmd[1] - f1)
        f2 += alpha * (cmd[2] - f2)
        f3 += alpha * (cmd[3] - f3)
        self._f = (f0, f1, f2, f3)
        mx = self._mix_rows
        thrust = (mx[0][0] * f0 + mx[0][1] * f1 + mx[0][2] * f2 + mx[0][3] * f3) * (
            self.ceiling_factor()
        )
        tau_x = mx[1][0] * f0 + mx[1][1] * f1 + mx[1][2] * f2 + mx[1][3] * f3
        tau_y = mx[2][0] * f0 + mx[2][1] * f1 + mx[2][2] * f2 + mx[2][3] * f3
        tau_z = mx[3][0] * f0 + mx[3][1] * f1 + mx[3][2] * f2 + mx[3][3] * f3
        R = self._R
        vx, vy, vz = self._v
        ex, ey, ez = force[0], force[1], force[2]
        k = dt_s / p.mass_kg
        drag = p.drag_n_s_per_m
        vx += k * (R[0][2] * thrust - drag * vx + ex)
        vy += k * (R[1][2] * thrust - drag * vy + ey)
        vz += k * (R[2][2] * thrust - drag * vz - p.weight_n + ez)
        px, py, pz = self._p
        self._p = (px + dt_s * vx, py + dt_s * vy, pz + dt_s * vz)
        self._v = (vx, vy, vz)
        ix, iy, iz = p.inertia_kg_m2
        wx, wy, wz = self._w
        hx, hy, hz = ix * wx, iy * wy, iz * wz
        wx, wy, wz = (
            wx + dt_s * (tau_x - (wy * hz - wz * hy)) / ix,
            wy + dt_s * (tau_y - (wz * hx - wx * hz)) / iy,
            wz + dt_s * (tau_z - (wx * hy - wy * hx)) / iz,
        )
        self._w = (wx, wy, wz)
        angle = dt_s * math.sqrt(wx * wx + wy * wy + wz * wz)
        if angle > 0:
            self._R = _rotated(R, (dt_s * wx / angle, dt_s * wy / angle, dt_s * wz / angle), angle)


def _mixed(
    rows: list[list[float]], wrench: tuple[float, float, float, float], top: float
) -> tuple[float, float, float, float]:
    """Motor thrusts ``rows @ wrench``, each limited to [0, top]."""
    t, x, y, z = wrench
    f = [min(top, max(0.0, r[0] * t + r[1] * x + r[2] * y + r[3] * z)) for r in rows]
    return (f[0], f[1], f[2], f[3])


def _vec3(value: Array | Sequence[float]) -> Vec3:
    x, y, z = (float(c) for c in np.asarray(value, np.float64).reshape(3))
    return (x, y, z)


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

"""A small quadrotor: rigid body, four motors with first-order response, and the onboard
attitude and velocity loops of a flight controller such as the Crazyflie's.

World frame: x, y horizontal, z up (metres). Body frame: x forward, y left, z up. Motors in
an X: front-left, front-right, back-right, back-left. Plain numpy.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

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


@dataclass
class Quadrotor:
    """The vehicle's state and its integration. ``p_m``, ``v_mps`` in the world frame;
    ``R_world_body``; ``omega_rad_s`` in the body frame; ``thrust_n`` per motor."""

    params: QuadrotorParams = field(default_factory=QuadrotorParams)
    gains: OnboardGains = field(default_factory=OnboardGains)
    p_m: Array = field(default_factory=lambda: np.zeros(3))
    v_mps: Array = field(default_factory=lambda: np.zeros(3))
    R_world_body: Array = field(default_factory=lambda: np.eye(3))
    omega_rad_s: Array = field(default_factory=lambda: np.zeros(3))
    thrust_n: Array = field(default_factory=lambda: np.zeros(4))
    ceiling_z_m: float | None = None

    def __post_init__(self) -> None:
        self._mix = mixer(self.params)
        self._unmix = np.linalg.inv(self._mix)
        self._mix_rows = self._mix.tolist()
        self._unmix_rows = self._unmix.tolist()
        self.thrust_n = np.full(4, self.params.weight_n / 4)  # start in hover

    @staticmethod
    def hovering(
        params: QuadrotorParams, p_m: Array, yaw_rad: float, gains: OnboardGains | None = None
    ) -> Quadrotor:
        """A vehicle hovering at ``p_m`` with heading ``yaw_rad``."""
        q = Quadrotor(params, gains or OnboardGains(), np.array(p_m, np.float64))
        q.R_world_body = rot_z(yaw_rad)
        return q

    @property
    def yaw_rad(self) -> float:
        """Heading of the body x axis."""
        return math.atan2(float(self.R_world_body[1, 0]), float(self.R_world_body[0, 0]))

    def ceiling_factor(self) -> float:
        """Thrust gain near a ceiling: 1 / (1 - (r / 4d)^2), capped at 1.5."""
        if self.ceiling_z_m is None:
            return 1.0
        d = max(self.ceiling_z_m - self.p_m[2], 1e-3)
        ratio = self.params.prop_radius_m / (4.0 * d)
        return float(min(1.5, 1.0 / max(1e-3, 1.0 - ratio * ratio)))

    def motor_commands(self, v_sp_mps: Array, yaw_rate_sp: float, v_estimate_mps: Array) -> Array:
        """The onboard loops: world velocity setpoint and yaw rate -> motor thrust commands.

        Written out in scalars: it runs at the physics rate, where numpy's per-call overhead on
        3-vectors costs more than the arithmetic.
        """
        p, g = self.params, self.gains
        vsx, vsy, vsz = (float(c) for c in v_sp_mps)
        vex, vey, vez = (float(c) for c in v_estimate_mps)
        m = p.mass_kg
        fx = m * g.k_velocity * (vsx - vex)
        fy = m * g.k_velocity * (vsy - vey)
        fz = m * (g.k_velocity * (vsz - vez) + GRAVITY_MPS2)
        # limit the tilt of the thrust vector
        horizontal = math.hypot(fx, fy)
        max_h = max(fz, 0.1 * p.weight_n) * math.tan(g.max_tilt_rad)
        if horizontal > max_h:
            fx *= max_h / horizontal
            fy *= max_h / horizontal
        norm = math.sqrt(fx * fx + fy * fy + fz * fz)
        zx, zy, zz = fx / norm, fy / norm, fz / norm
        R = self.R_world_body.tolist()
        yaw = math.atan2(R[1][0], R[0][0])
        cx, cy = math.cos(yaw), math.sin(yaw)
        # y_b = z_b x x_c, normalised; x_b = y_b x z_b
        yx, yy, yz = -zz * cy, zz * cx, zx * cy - zy * cx
        n = math.sqrt(yx * yx + yy * yy + yz * yz)
        yx, yy, yz = yx / n, yy / n, yz / n
        xx, xy, xz = yy * zz - yz * zy, yz * zx - yx * zz, yx * zy - yy * zx
        des = ((xx, xy, xz), (yx, yy, yz), (zx, zy, zz))  # columns of R_des
        cols = (
            (R[0][0], R[1][0], R[2][0]),
            (R[0][1], R[1][1], R[2][1]),
            (R[0][2], R[1][2], R[2][2]),
        )

        def a(i: int, j: int) -> float:  # (R_des^T R)[i, j]
            d, c = des[i], cols[j]
            return float(d[0] * c[0] + d[1] * c[1] + d[2] * c[2])

        thrust = fx * cols[2][0] + fy * cols[2][1] + fz * cols[2][2]
        # attitude error: vee of the skew part of R_des^T R, body frame
        e_x = 0.5 * (a(2, 1) - a(1, 2))
        e_y = 0.5 * (a(0, 2) - a(2, 0))
        lim = g.max_rate_rad_s
        rate_x = min(lim, max(-lim, -g.k_attitude * e_x))
        rate_y = min(lim, max(-lim, -g.k_attitude * e_y))
        ix, iy, iz = p.inertia_kg_m2
        wx, wy, wz = self.omega_rad_s.tolist()
        hx, hy, hz = ix * wx, iy * wy, iz * wz  # angular momentum
        tau_x = g.k_rate * ix / 1.66e-5 * (rate_x - wx) + (wy * hz - wz * hy)
        tau_y = g.k_rate * iy / 1.66e-5 * (rate_y - wy) + (wz * hx - wx * hz)
        tau_z = g.k_yaw_rate * iz / 1.66e-5 * (float(yaw_rate_sp) - wz) + (wx * hy - wy * hx)
        wrench = (max(thrust, 0.0), tau_x, tau_y, tau_z)
        top = p.max_thrust_n
        return np.array(
            [
                min(top, max(0.0, sum(u * w for u, w in zip(row, wrench, strict=True))))
                for row in self._unmix_rows
            ]
        )

    def step(self, dt_s: float, motor_cmd_n: Array, force_world_n: Array | None = None) -> None:
        """Advance ``dt_s`` seconds (semi-implicit Euler), in scalars as ``motor_commands``."""
        p = self.params
        alpha = min(1.0, dt_s / p.motor_tau_s)
        f = [
            fi + alpha * (ci - fi)
            for fi, ci in zip(self.thrust_n.tolist(), np.asarray(motor_cmd_n).tolist(), strict=True)
        ]
        thrust, tau_x, tau_y, tau_z = (
            sum(u * fi for u, fi in zip(row, f, strict=True)) for row in self._mix_rows
        )
        thrust *= self.ceiling_factor()
        R = self.R_world_body.tolist()
        vx, vy, vz = self.v_mps.tolist()
        ex, ey, ez = (
            (0.0, 0.0, 0.0) if force_world_n is None else np.asarray(force_world_n).tolist()
        )
        k = dt_s / p.mass_kg
        drag = p.drag_n_s_per_m
        vx += k * (R[0][2] * thrust - drag * vx + ex)
        vy += k * (R[1][2] * thrust - drag * vy + ey)
        vz += k * (R[2][2] * thrust - drag * vz - p.weight_n + ez)
        px, py, pz = self.p_m.tolist()
        self.p_m = np.array([px + dt_s * vx, py + dt_s * vy, pz + dt_s * vz])
        self.v_mps = np.array([vx, vy, vz])
        self.thrust_n = np.array(f)
        ix, iy, iz = p.inertia_kg_m2
        wx, wy, wz = self.omega_rad_s.tolist()
        hx, hy, hz = ix * wx, iy * wy, iz * wz
        wx, wy, wz = (
            wx + dt_s * (tau_x - (wy * hz - wz * hy)) / ix,
            wy + dt_s * (tau_y - (wz * hx - wx * hz)) / iy,
            wz + dt_s * (tau_z - (wx * hy - wy * hx)) / iz,
        )
        self.omega_rad_s = np.array([wx, wy, wz])
        angle = dt_s * math.sqrt(wx * wx + wy * wy + wz * wz)
        if angle > 0:
            # R <- R @ exp([w dt]x) (Rodrigues), then Gram-Schmidt on the columns
            ax, ay, az = (dt_s * c / angle for c in (wx, wy, wz))
            sa, ca = math.sin(angle), 1.0 - math.cos(angle)
            dR = (
                (1 - ca * (ay * ay + az * az), -sa * az + ca * ax * ay, sa * ay + ca * ax * az),
                (sa * az + ca * ax * ay, 1 - ca * (ax * ax + az * az), -sa * ax + ca * ay * az),
                (-sa * ay + ca * ax * az, sa * ax + ca * ay * az, 1 - ca * (ax * ax + ay * ay)),
            )
            M = [[sum(R[i][k] * dR[k][j] for k in range(3)) for j in range(3)] for i in range(3)]
            c0 = [M[0][0], M[1][0], M[2][0]]
            n0 = math.sqrt(sum(c * c for c in c0))
            c0 = [c / n0 for c in c0]
            c1 = [M[0][1], M[1][1], M[2][1]]
            d = sum(a * b for a, b in zip(c0, c1, strict=True))
            c1 = [b - d * a for a, b in zip(c0, c1, strict=True)]
            n1 = math.sqrt(sum(c * c for c in c1))
            c1 = [c / n1 for c in c1]
            c2 = [
                c0[1] * c1[2] - c0[2] * c1[1],
                c0[2] * c1[0] - c0[0] * c1[2],
                c0[0] * c1[1] - c0[1] * c1[0],
            ]
            self.R_world_body = np.array([c0, c1, c2]).T

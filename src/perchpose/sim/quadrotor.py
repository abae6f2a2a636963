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
        """The onboard loops: world velocity setpoint and yaw rate -> motor thrust commands."""
        p, g = self.params, self.gains
        a_des = g.k_velocity * (np.asarray(v_sp_mps) - v_estimate_mps)
        f_des = p.mass_kg * (a_des + np.array([0.0, 0.0, GRAVITY_MPS2]))
        # limit the tilt of the thrust vector
        horizontal = math.hypot(f_des[0], f_des[1])
        max_h = max(f_des[2], 0.1 * p.weight_n) * math.tan(g.max_tilt_rad)
        if horizontal > max_h:
            f_des[:2] *= max_h / horizontal
        z_b = f_des / np.linalg.norm(f_des)
        x_c = np.array([math.cos(self.yaw_rad), math.sin(self.yaw_rad), 0.0])
        y_b = np.cross(z_b, x_c)
        y_b /= np.linalg.norm(y_b)
        R_des = np.stack([np.cross(y_b, z_b), y_b, z_b], axis=1)
        thrust = float(f_des @ self.R_world_body[:, 2])
        # attitude error (vee of the skew part of R_des^T R), body frame
        E = R_des.T @ self.R_world_body - self.R_world_body.T @ R_des
        e_att = 0.5 * np.array([E[2, 1], E[0, 2], E[1, 0]])
        rate_sp = np.clip(-g.k_attitude * e_att, -g.max_rate_rad_s, g.max_rate_rad_s)
        rate_sp[2] = yaw_rate_sp
        inertia = np.array(p.inertia_kg_m2)
        k = np.array([g.k_rate, g.k_rate, g.k_yaw_rate]) * inertia / 1.66e-5
        torque = k * (rate_sp - self.omega_rad_s) + np.cross(
            self.omega_rad_s, inertia * self.omega_rad_s
        )
        wrench = np.array([max(thrust, 0.0), *torque])
        return np.asarray(np.clip(self._unmix @ wrench, 0.0, p.max_thrust_n), np.float64)

    def step(self, dt_s: float, motor_cmd_n: Array, force_world_n: Array | None = None) -> None:
        """Advance ``dt_s`` seconds (semi-implicit Euler)."""
        p = self.params
        alpha = min(1.0, dt_s / p.motor_tau_s)
        self.thrust_n = self.thrust_n + alpha * (np.asarray(motor_cmd_n) - self.thrust_n)
        wrench = self._mix @ self.thrust_n
        thrust = wrench[0] * self.ceiling_factor()
        force = self.R_world_body[:, 2] * thrust - p.drag_n_s_per_m * self.v_mps
        force = force + np.array([0.0, 0.0, -p.weight_n])
        if force_world_n is not None:
            force = force + force_world_n
        self.v_mps = self.v_mps + dt_s * force / p.mass_kg
        self.p_m = self.p_m + dt_s * self.v_mps
        inertia = np.array(p.inertia_kg_m2)
        omega_dot = (wrench[1:] - np.cross(self.omega_rad_s, inertia * self.omega_rad_s)) / inertia
        self.omega_rad_s = self.omega_rad_s + dt_s * omega_dot
        w = self.omega_rad_s * dt_s
        angle = float(np.linalg.norm(w))
        if angle > 0:
            axis = w / angle
            K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
            dR = np.eye(3) + math.sin(angle) * K + (1 - math.cos(angle)) * (K @ K)
            self.R_world_body = self.R_world_body @ dR
            u, _, vt = np.linalg.svd(self.R_world_body)  # keep it a rotation
            self.R_world_body = u @ vt

"""RotorPy's ``Multirotor`` as the perching simulation's plant, to check ours against it in
closed loop (needs ``rotorpy``, a ``dev`` dependency).

``RotorpyQuadrotor`` keeps this package's flight controller (the onboard velocity, attitude
and rate loops of ``perchpose.sim.quadrotor``) and hands each physics step's motor commands to
RotorPy as rotor speeds: RotorPy's rigid body, rotor dynamics and aerodynamics (rotor drag,
body drag) integrate the step with scipy's RK45. RotorPy has no ceiling effect and no motor
mismatch, so flights compared against it leave both out.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

from perchpose.errors import PerchposeError
from perchpose.sim.quadrotor import OnboardGains, Quadrotor, QuadrotorParams

Array = NDArray[np.float64]
# RotorPy's Crazyflie has no body drag; the values ours uses are given to both
BODY_DRAG = {"c_Dx": 9.2e-4, "c_Dy": 9.2e-4, "c_Dz": 1.8e-3}


def _rotorpy() -> tuple[Any, Any]:
    try:
        from rotorpy.vehicles import crazyflie_params, multirotor
    except ImportError as exc:
        raise PerchposeError("RotorPy as the plant needs rotorpy: pip install rotorpy") from exc
    return multirotor, crazyflie_params


def rotorpy_crazyflie() -> tuple[QuadrotorParams, dict[str, Any]]:
    """RotorPy's Crazyflie 2.0 (with our body drag and no motor noise), and the same vehicle
    as ``QuadrotorParams``."""
    _, crazyflie = _rotorpy()
    rp: dict[str, Any] = {**crazyflie.quad_params, **BODY_DRAG, "motor_noise_std": 0.0}
    k_eta = float(rp["k_eta"])
    hub = np.asarray(rp["rotor_pos"]["r1"], np.float64)
    ours = QuadrotorParams(
        mass_kg=float(rp["mass"]),
        inertia_kg_m2=(float(rp["Ixx"]), float(rp["Iyy"]), float(rp["Izz"])),
        arm_m=float(hub[0]),
        max_thrust_n=k_eta * float(rp["rotor_speed_max"]) ** 2,
        motor_tau_s=float(rp["tau_m"]),
        k_thrust=k_eta,
        yaw_moment_m=float(rp["k_m"]) / k_eta,
        rotor_drag_kg_per_rad=float(rp["k_d"]),
        inflow_drag_kg_per_rad=float(rp["k_z"]),
        body_drag_n_per_mps2=(float(rp["c_Dx"]), float(rp["c_Dz"])),
    )
    return ours, rp


def _quaternion_xyzw(R: Array) -> Array:
    """The unit quaternion (x, y, z, w) of a rotation matrix (Shepperd's method)."""
    trace = float(np.trace(R))
    if trace > 0:
        s = 2.0 * math.sqrt(trace + 1.0)
        q = [(R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s, 0.25 * s]
    else:
        i = int(np.argmax(np.diag(R)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * math.sqrt(1.0 + R[i, i] - R[j, j] - R[k, k])
        q = [0.0, 0.0, 0.0, (R[k, j] - R[j, k]) / s]
        q[i] = 0.25 * s
        q[j] = (R[j, i] + R[i, j]) / s
        q[k] = (R[k, i] + R[i, k]) / s
    out = np.array(q, np.float64)
    return out / np.linalg.norm(out)


def _matrix(q_xyzw: Array) -> Array:
    x, y, z, w = (float(v) for v in q_xyzw)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


class RotorpyQuadrotor(Quadrotor):
    """Our flight controller on RotorPy's ``Multirotor`` (``rotorpy_params`` its vehicle,
    ``params`` the same one in our terms, as ``rotorpy_crazyflie`` gives them)."""

    def __init__(
        self,
        params: QuadrotorParams,
        rotorpy_params: dict[str, Any],
        gains: OnboardGains | None = None,
        p_m: Array | None = None,
    ) -> None:
        super().__init__(params, gains, p_m)
        multirotor, _ = _rotorpy()
        self._multirotor = multirotor.Multirotor(
            rotorpy_params, control_abstraction="cmd_motor_speeds", aero=True
        )

    @staticmethod
    def hovering_on_rotorpy(
        params: QuadrotorParams,
        rotorpy_params: dict[str, Any],
        p_m: Array,
        yaw_rad: float,
        gains: OnboardGains | None = None,
    ) -> RotorpyQuadrotor:
        """A vehicle hovering at ``p_m`` with heading ``yaw_rad``, RotorPy flying it."""
        q = RotorpyQuadrotor(params, rotorpy_params, gains, np.asarray(p_m, np.float64))
        hovering = Quadrotor.hovering(params, p_m, yaw_rad, gains)
        q.R_world_body = hovering.R_world_body
        return q

    def _step(self, dt_s: float, cmd: tuple[float, float, float, float]) -> None:
        p = self.params
        speeds = np.array(
            [
                math.sqrt(max(0.0, f) / p.k_thrust) * math.sqrt(scale)
                for f, scale in zip(cmd, self.thrust_scale, strict=True)
            ]
        )
        state = {
            "x": np.array(self._p),
            "v": np.array(self._v),
            "q": _quaternion_xyzw(np.array(self._R)),
            "w": np.array(self._w),
            "wind": np.array(self.wind_mps),
            "rotor_speeds": np.array(self._rotor),
        }
        new = self._multirotor.step(state, {"cmd_motor_speeds": speeds}, dt_s)
        self.p_m = new["x"]
        self.v_mps = new["v"]
        self.R_world_body = _matrix(new["q"])
        self.omega_rad_s = new["w"]
        self.rotor_speed_rad_s = new["rotor_speeds"]

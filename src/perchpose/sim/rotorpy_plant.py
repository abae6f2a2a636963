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
from perchpose.geometry import quaternion_xyzw, rotation_from_quaternion
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


class RotorpyQuadrotor(Quadrotor):
    """Our flight controller on RotorPy's ``Multirotor`` (``rotorpy_params`` its vehicle,
    ``params`` the same one in our terms, as ``rotorpy_crazyflie`` gives them)."""

    takes_plate_forces = False  # RotorPy integrates it: the plate is only watched

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
            "q": np.array(quaternion_xyzw(np.array(self._R))),
            "w": np.array(self._w),
            "wind": np.array(self.wind_mps),
            "rotor_speeds": np.array(self._rotor),
        }
        new = self._multirotor.step(state, {"cmd_motor_speeds": speeds}, dt_s)
        self.p_m = new["x"]
        self.v_mps = new["v"]
        qx, qy, qz, qw = (float(v) for v in new["q"])
        self.R_world_body = rotation_from_quaternion(qw, qx, qy, qz)
        self.omega_rad_s = new["w"]
        self.rotor_speed_rad_s = new["rotor_speeds"]

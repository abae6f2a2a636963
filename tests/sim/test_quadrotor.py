import math

import numpy as np
import pytest

from perchpose.errors import VehicleConfigError
from perchpose.sim.quadrotor import GRAVITY_MPS2, Quadrotor, QuadrotorParams, mixer


def _fly(
    q: Quadrotor, v_sp: np.ndarray, yaw_rate: float, seconds: float, dt: float = 0.002
) -> None:
    for _ in range(int(seconds / dt)):
        q.step(dt, q.motor_commands(v_sp, yaw_rate, q.v_mps))


def test_hover_thrust_equals_weight() -> None:
    params = QuadrotorParams()
    q = Quadrotor.hovering(params, np.array([0.0, 0.0, 1.0]), 0.3)
    _fly(q, np.zeros(3), 0.0, 2.0)
    assert float(np.sum(q.thrust_n)) == pytest.approx(params.mass_kg * GRAVITY_MPS2, rel=1e-3)
    assert np.linalg.norm(q.v_mps) < 1e-3
    assert np.linalg.norm(q.p_m - [0.0, 0.0, 1.0]) < 1e-3


def test_mixer_is_invertible_and_balanced() -> None:
    M = mixer(QuadrotorParams())
    assert np.linalg.matrix_rank(M) == 4
    equal = M @ np.full(4, 0.1)
    np.testing.assert_allclose(equal[1:], 0.0, atol=1e-15)


@pytest.mark.parametrize("axis", [0, 1, 2])
def test_velocity_step_settles(axis: int) -> None:
    q = Quadrotor.hovering(QuadrotorParams(), np.array([0.0, 0.0, 1.0]), 0.0)
    v_sp = np.zeros(3)
    v_sp[axis] = 0.2
    _fly(q, v_sp, 0.0, 2.0)
    # proportional onboard loop against drag: within 10 % and steady
    assert q.v_mps[axis] == pytest.approx(0.2, rel=0.1)
    before = q.v_mps.copy()
    _fly(q, v_sp, 0.0, 0.5)
    np.testing.assert_allclose(q.v_mps, before, atol=2e-3)
    _fly(q, np.zeros(3), 0.0, 2.0)
    assert np.linalg.norm(q.v_mps) < 5e-3


def test_yaw_rate_is_followed() -> None:
    q = Quadrotor.hovering(QuadrotorParams(), np.array([0.0, 0.0, 1.0]), 0.0)
    _fly(q, np.zeros(3), 0.5, 1.0)
    assert math.degrees(q.yaw_rad) == pytest.approx(math.degrees(0.5), abs=2.0)


def test_ceiling_effect_pushes_up_near_the_plate() -> None:
    q = Quadrotor.hovering(QuadrotorParams(), np.array([0.0, 0.0, 1.99]), 0.0)
    q.ceiling_z_m = 2.0
    assert q.ceiling_factor() > 1.05
    q.ceiling_z_m = 3.0
    assert q.ceiling_factor() == pytest.approx(1.0, abs=1e-3)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"mass_kg": -0.01}, "mass must be positive"),
        ({"max_thrust_n": 0.05}, "thrust-to-weight"),
        ({"inertia_kg_m2": (1e-5, 0.0, 1e-5)}, "inertia"),
    ],
)
def test_bad_vehicles(kwargs: dict[str, object], message: str) -> None:
    with pytest.raises(VehicleConfigError, match=message):
        QuadrotorParams(**kwargs)  # type: ignore[arg-type]

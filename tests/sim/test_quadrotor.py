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


def test_a_velocity_gain_set_by_the_pilot_makes_the_horizontal_loop_faster() -> None:
    """As the pilot sets the flight controller's parameter: 6 /s instead of 4.3 /s along x and
    y (z keeps its own), and the vehicle's own back on None."""

    def speed_after(gain: float | None, axis: int) -> float:
        q = Quadrotor.hovering(QuadrotorParams(), np.array([0.0, 0.0, 1.0]), 0.0)
        assert q.set_velocity_gain(gain)
        v_sp = np.zeros(3)
        v_sp[axis] = 0.2
        _fly(q, v_sp, 0.0, 0.15)
        return float(q.v_mps[axis])

    assert speed_after(6.0, 0) > 1.15 * speed_after(None, 0)
    assert speed_after(6.0, 1) > 1.15 * speed_after(None, 1)
    assert speed_after(6.0, 2) == pytest.approx(speed_after(None, 2), rel=1e-12)


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


def test_the_ceiling_effect_acts_only_under_the_plate() -> None:
    """Beside a 20 cm plate, 1 cm below its plane, the rotors get nothing from it; under its
    edge, the rotors under it get the whole gain and those beyond it none; and the vehicle's
    climb follows: it climbs under the plate, holds beside it."""
    params = QuadrotorParams()

    def beside(x_m: float) -> Quadrotor:
        q = Quadrotor.hovering(params, np.array([x_m, 0.0, 1.99 - params.rotor_plane_m]), 0.0)
        q.ceiling_z_m, q.ceiling_half_size_m = 2.0, 0.10
        return q

    assert beside(0.0).ceiling_factor() > 1.05
    assert beside(0.30).ceiling_factor() == 1.0
    edge = beside(0.10)  # the hubs at x = 0.10 +- the arm: two under the plate, two beyond
    gains = [edge.ceiling_factor(i) for i in range(4)]
    inside = [
        g for i, g in enumerate(gains) if edge.point_in_world((*edge.hubs_m[i], 0.0))[0] < 0.1
    ]
    assert len(inside) == 2
    assert all(g > 1.05 for g in inside)
    assert sorted(gains)[:2] == [1.0, 1.0]
    rises = []
    for x_m in (0.0, 0.30):
        q = beside(x_m)
        # the motors held at the hover's thrust: only the ceiling's share moves the vehicle
        hover = np.full(4, params.weight_n / 4)
        for _ in range(50):
            q.step(0.001, hover)
        rises.append(float(q.v_mps[2]))
    assert rises[0] > 0.01
    assert abs(rises[1]) < 1e-6


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


def test_the_accelerometer_reads_the_wind_s_push_along_body_x_and_y() -> None:
    """At rest the accelerometer reads +g along body z. In a steady wind the vehicle leans
    into it: the reading is still g straight up in the world frame (no acceleration), and its
    body x/y part is the drag the tilt holds off. A gust shows at once, before it has moved
    the vehicle."""
    q = Quadrotor.hovering(QuadrotorParams(), np.array([0.0, 0.0, 1.0]), 0.7)
    _fly(q, np.zeros(3), 0.0, 0.5)
    np.testing.assert_allclose(q.specific_force_body_mps2, [0.0, 0.0, GRAVITY_MPS2], atol=1e-3)
    q.wind_mps = (3.0, -1.0, 0.0)
    _fly(q, np.zeros(3), 0.0, 6.0)
    f_world = q.R_world_body @ q.specific_force_body_mps2
    np.testing.assert_allclose(f_world, [0.0, 0.0, GRAVITY_MPS2], atol=0.02)
    push = q.R_world_body @ np.array([*q.specific_force_body_mps2[:2], 0.0])
    assert np.linalg.norm(push[:2]) > 0.5
    assert np.dot(push[:2], [3.0, -1.0]) / (np.linalg.norm(push[:2]) * math.hypot(3.0, 1.0)) > 0.99
    before = q.specific_force_body_mps2.copy()
    v_before = q.v_mps.copy()
    q.wind_mps = (6.0, -2.0, 0.0)
    _fly(q, np.zeros(3), 0.0, 0.05)
    jump = np.linalg.norm(q.specific_force_body_mps2[:2] - before[:2])
    assert jump > 0.5  # the push has grown by most of itself in 50 ms
    assert np.linalg.norm(q.v_mps - v_before) < 0.1

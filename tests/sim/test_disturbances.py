import numpy as np
import pytest

from perchpose.errors import DisturbanceConfigError
from perchpose.sim.disturbances import Disturbances, OdometryModel, VehicleDraw


def test_draws_stay_in_their_ranges_and_repeat_with_the_seed() -> None:
    d = Disturbances()
    draws = [VehicleDraw.draw(d, 20.0, np.random.default_rng(seed)) for seed in range(200)]
    scales = np.array([x.motor_scale for x in draws])
    assert scales.min() >= 0.97
    assert scales.max() <= 1.03
    assert scales.std() > 0.01  # the motors differ
    for x in draws:
        assert 0.92 <= x.battery_start <= 1.0
        assert all(0 <= a < b <= 21.0 for a, b in x.bursts)
        np.testing.assert_allclose(x.attitude_bias @ x.attitude_bias.T, np.eye(3), atol=1e-12)
    # about one burst per 20 s flight, each 0.2-1 s
    assert 0.6 < np.mean([len(x.bursts) for x in draws]) < 1.4
    again = VehicleDraw.draw(d, 20.0, np.random.default_rng(7))
    assert again.motor_scale == draws[7].motor_scale
    assert again.bursts == draws[7].bursts


def test_the_battery_sags_and_bursts_blind_the_camera() -> None:
    draw = VehicleDraw((1.0, 1.0, 1.0, 1.0), np.eye(3), 0.98, 0.002, ((3.0, 4.0),))
    assert draw.thrust_scale(0.0) == pytest.approx((0.98,) * 4)
    assert draw.thrust_scale(10.0) == pytest.approx((0.96,) * 4)
    assert draw.in_burst(3.5)
    assert not draw.in_burst(4.0)
    assert not draw.in_burst(2.9)


def test_a_clean_lab_draws_nothing() -> None:
    draw = VehicleDraw.draw(Disturbances.none(), 20.0, np.random.default_rng(1))
    assert draw.motor_scale == (1.0, 1.0, 1.0, 1.0)
    assert draw.bursts == ()
    np.testing.assert_allclose(draw.attitude_bias, np.eye(3))
    assert draw.thrust_scale(15.0) == (1.0, 1.0, 1.0, 1.0)


def test_odometry_drifts_like_a_state_estimate() -> None:
    drifts = []
    for seed in range(40):
        odometry = OdometryModel(Disturbances(), np.zeros(3), np.random.default_rng(seed))
        for _ in range(600):  # 20 s at 30 Hz, hovering at the origin
            odometry.update(np.zeros(3), np.zeros(3), 1 / 30)
        drifts.append(np.linalg.norm(odometry.p_m[:2]))
    # centimetres after 20 s (about 7 cm median): neither exact nor useless
    assert 0.02 < float(np.median(drifts)) < 0.15
    clean = OdometryModel(Disturbances.none(), np.zeros(3), np.random.default_rng(0))
    for _ in range(600):
        clean.update(np.zeros(3), np.zeros(3), 1 / 30)
    np.testing.assert_allclose(clean.p_m, 0.0)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"thrust_mismatch": -0.1}, "thrust_mismatch"),
        ({"latency_jitter": 1.5}, "probability"),
        ({"burst_s": (1.0, 0.5)}, "burst_s"),
        ({"battery_start": (0.9, 1.2)}, "battery_start"),
    ],
)
def test_bad_disturbances(kwargs: dict[str, object], message: str) -> None:
    with pytest.raises(DisturbanceConfigError, match=message):
        Disturbances(**kwargs)  # type: ignore[arg-type]

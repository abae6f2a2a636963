import math

import numpy as np
import pytest

from perchpose.errors import WindConfigError
from perchpose.sim.wind import (
    WIND_LEVELS,
    DrydenWind,
    WindLevel,
    scale_lengths_m,
    vertical_intensity_ratio,
    wind_level,
)


def test_named_levels_meet_their_definitions() -> None:
    assert WIND_LEVELS["none"].calm
    assert WIND_LEVELS["light"].mean_mps >= 1.5
    assert WIND_LEVELS["light"].turbulence_sigma_mps >= 0.5
    assert WIND_LEVELS["moderate"].mean_mps >= 3.0
    assert WIND_LEVELS["moderate"].turbulence_sigma_mps >= 1.0
    assert WIND_LEVELS["strong"].mean_mps >= 4.5
    assert WIND_LEVELS["strong"].turbulence_sigma_mps >= 1.5


def test_low_altitude_scale_lengths() -> None:
    # at the 10 ft floor: L_w = 10 ft, L_u = 10 / 0.18523^1.2 ft
    l_uv, l_w = scale_lengths_m(1.0)
    assert l_w == pytest.approx(3.048)
    assert l_uv == pytest.approx(10 / 0.18523**1.2 * 0.3048, rel=1e-4)
    assert scale_lengths_m(1.0) == scale_lengths_m(2.5)  # both under the floor
    assert scale_lengths_m(30.0)[1] == pytest.approx(30.0)
    assert vertical_intensity_ratio(1.0) == pytest.approx(0.18523**0.4, rel=1e-4)


def _long_wind(level: WindLevel, seed: int, direction: float = 0.0) -> np.ndarray:
    wind = DrydenWind(level, 0.05, np.random.default_rng(seed), direction_rad=direction)
    return wind.samples(40_000)  # 2,000 s: over a hundred correlation times


def test_mean_direction_and_intensities() -> None:
    level = WindLevel(3.0, 1.0)
    samples = np.concatenate([_long_wind(level, seed, math.pi / 2) for seed in range(6)])
    # the mean wind blows along +y
    assert samples[:, 1].mean() == pytest.approx(3.0, abs=0.1)
    assert samples[:, 0].mean() == pytest.approx(0.0, abs=0.1)
    # gusts along the wind (y here) and across it (x) have sigma, vertical ones sigma_w
    assert samples[:, 1].std() == pytest.approx(1.0, rel=0.1)
    assert samples[:, 0].std() == pytest.approx(1.0, rel=0.1)
    assert samples[:, 2].std() == pytest.approx(vertical_intensity_ratio(2.0), rel=0.1)


def test_gusts_are_correlated_over_the_scale_length() -> None:
    level = WindLevel(3.0, 1.0)
    wind = DrydenWind(level, 0.05, np.random.default_rng(1))
    tau_u = wind.time_constants_s[0]
    u = np.concatenate([_long_wind(level, seed)[:, 0] - 3.0 for seed in range(6)])
    lag = int(round(tau_u / 0.05))
    # a first-order (longitudinal) Dryden gust: autocorrelation exp(-1) one time constant on
    rho = float(np.corrcoef(u[:-lag], u[lag:])[0, 1])
    assert rho == pytest.approx(math.exp(-1), abs=0.08)
    # and not a white noise: the next sample is nearly the same
    assert float(np.corrcoef(u[:-1], u[1:])[0, 1]) > 0.99


def test_same_seed_same_wind_and_calm_is_still() -> None:
    a = DrydenWind(WIND_LEVELS["light"], 0.01, np.random.default_rng(7)).samples(50)
    b = DrydenWind(WIND_LEVELS["light"], 0.01, np.random.default_rng(7)).samples(50)
    np.testing.assert_array_equal(a, b)
    calm = DrydenWind(WIND_LEVELS["none"], 0.01, np.random.default_rng(7)).samples(50)
    assert not calm.any()


def test_the_wind_now_is_the_last_sample_and_draws_nothing() -> None:
    """``now`` (the wind a vehicle hovers in before its run) is the wind the last step gave,
    or before any step the stationary draw the gusts start from; asking for it changes no
    later sample."""
    asked = DrydenWind(WIND_LEVELS["moderate"], 0.01, np.random.default_rng(3), 0.7)
    plain = DrydenWind(WIND_LEVELS["moderate"], 0.01, np.random.default_rng(3), 0.7)
    first = np.array(asked.now())
    assert np.hypot(first[0], first[1]) > 0.5  # the mean, 3 m/s, and a gust beside it
    assert asked.now() == tuple(first)
    sample = asked.step()
    assert asked.now() == sample
    np.testing.assert_array_equal(asked.samples(20), plain.samples(21)[1:])


@pytest.mark.parametrize(
    ("mean", "gust", "message"),
    [
        (-1.0, 0.5, "non-negative"),
        (20.0, 0.5, "beyond"),
        (2.0, math.nan, "non-negative"),
    ],
)
def test_bad_wind(mean: float, gust: float, message: str) -> None:
    with pytest.raises(WindConfigError, match=message):
        WindLevel(mean, gust)


def test_unknown_level_names_the_choices() -> None:
    with pytest.raises(WindConfigError, match="none, light, moderate, strong"):
        wind_level("breezy")

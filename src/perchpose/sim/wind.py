"""Wind as flight-dynamics work models it: a mean wind plus Dryden turbulence.

The turbulence follows the Dryden spectra of MIL-F-8785C / MIL-HDBK-1797 for low altitude
(below 1,000 ft). With h the height in feet and V the airspeed through the air mass (Taylor's
frozen-turbulence hypothesis; for a hovering vehicle, the mean wind speed):

- scale lengths L_w = h and L_u = L_v = h / (0.177 + 0.000823 h)^1.2 (feet);
- intensities sigma_u = sigma_v = sigma and sigma_w = sigma (0.177 + 0.000823 h)^0.4;
- spectra shaped by H_u(s) ~ 1 / (1 + (L_u / V) s) (longitudinal, along the mean wind) and
  H_v(s), H_w(s) ~ (1 + sqrt(3) (L / V) s) / (1 + (L / V) s)^2 (lateral, vertical).

A vehicle perching under a plate flies a metre or two above the floor, below the model's
lower edge of 10 ft: h is held at 10 ft there, as the handbook's low-altitude model does. V is
floored at ``MIN_AIRSPEED_MPS`` so that turbulence without mean wind stays defined.

Each component is a discrete filter driven by seeded Gaussian noise and scaled to the exact
stationary standard deviation of its own discrete form, so the intensities hold at any step.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from perchpose.errors import WindConfigError

Array = NDArray[np.float64]

FT_M = 0.3048
LOW_ALTITUDE_FLOOR_FT = 10.0
MIN_AIRSPEED_MPS = 0.5
MAX_WIND_MPS = 15.0


@dataclass(frozen=True)
class WindLevel:
    """A mean wind speed and a turbulence intensity (standard deviation of the horizontal
    gusts), both m/s."""

    mean_mps: float
    turbulence_sigma_mps: float

    def __post_init__(self) -> None:
        for name, value in (
            ("wind speed", self.mean_mps),
            ("turbulence", self.turbulence_sigma_mps),
        ):
            if not math.isfinite(value) or value < 0:
                raise WindConfigError(f"{name} must be a non-negative number, got {value} m/s")
            if value > MAX_WIND_MPS:
                raise WindConfigError(
                    f"{name} {value:g} m/s is beyond what a nano drone can fly in "
                    f"(at most {MAX_WIND_MPS:g} m/s)"
                )

    @property
    def calm(self) -> bool:
        return self.mean_mps == 0 and self.turbulence_sigma_mps == 0


# named levels: mean wind and turbulence intensity, m/s
WIND_LEVELS = {
    "none": WindLevel(0.0, 0.0),
    "light": WindLevel(1.5, 0.5),
    "moderate": WindLevel(3.0, 1.0),
    "strong": WindLevel(4.5, 1.5),
}


def wind_level(name: str) -> WindLevel:
    """The named level, or a ``WindConfigError`` naming the choices."""
    try:
        return WIND_LEVELS[name]
    except KeyError:
        raise WindConfigError(
            f"unknown wind level {name!r} (choose {', '.join(WIND_LEVELS)}, or give "
            "--wind-mps and --gust-mps)"
        ) from None


def scale_lengths_m(height_m: float) -> tuple[float, float]:
    """(L_u = L_v, L_w) in metres at ``height_m`` (low-altitude Dryden, h floored at 10 ft)."""
    h_ft = max(LOW_ALTITUDE_FLOOR_FT, height_m / FT_M)
    l_w_ft = h_ft
    l_uv_ft = h_ft / (0.177 + 0.000823 * h_ft) ** 1.2
    return l_uv_ft * FT_M, l_w_ft * FT_M


def vertical_intensity_ratio(height_m: float) -> float:
    """sigma_w / sigma_u at ``height_m`` (low-altitude Dryden)."""
    h_ft = max(LOW_ALTITUDE_FLOOR_FT, height_m / FT_M)
    return float((0.177 + 0.000823 * h_ft) ** 0.4)


class _FirstOrder:
    """sigma / (1 + T s) shaping of white noise: an exactly discretised Gauss-Markov process."""

    def __init__(self, sigma: float, tau_s: float, dt_s: float) -> None:
        self.a = math.exp(-dt_s / tau_s)
        self.b = sigma * math.sqrt(1.0 - self.a * self.a)
        self.y = 0.0

    def start(self, sigma: float, n: float) -> None:
        self.y = sigma * n

    def step(self, n: float) -> None:
        self.y = self.a * self.y + self.b * n

    @property
    def value(self) -> float:
        return self.y


class _DrydenTransverse:
    """(1 + sqrt(3) T s) / (1 + T s)^2 shaping: two first-order stages, x1 a unit Gauss-Markov
    process and x2 = x1 through 1 / (1 + T s); output sqrt(3) x1 + (1 - sqrt(3)) x2, scaled to
    ``sigma`` with the stationary covariance of this discrete system."""

    def __init__(self, sigma: float, tau_s: float, dt_s: float) -> None:
        a = math.exp(-dt_s / tau_s)
        self.a = a
        self.q = math.sqrt(1.0 - a * a)
        self.c1, self.c2 = math.sqrt(3.0), 1.0 - math.sqrt(3.0)
        # stationary covariance of (x1, x2): x1' = a x1 + q n, x2' = a x2 + (1 - a) x1
        p11 = 1.0
        p12 = a * (1 - a) * p11 / (1 - a * a)
        p22 = ((1 - a) ** 2 * p11 + 2 * a * (1 - a) * p12) / (1 - a * a)
        var = self.c1**2 * p11 + 2 * self.c1 * self.c2 * p12 + self.c2**2 * p22
        self.gain = sigma / math.sqrt(var)
        self._p = (p11, p12, p22)
        self.x1 = 0.0
        self.x2 = 0.0

    def start(self, n1: float, n2: float) -> None:
        """A draw from the stationary distribution (no start-up transient)."""
        p11, p12, p22 = self._p
        self.x1 = math.sqrt(p11) * n1
        r = p12 / math.sqrt(p11)
        self.x2 = r * n1 + math.sqrt(max(0.0, p22 - r * r)) * n2

    def step(self, n: float) -> None:
        self.x2 = self.a * self.x2 + (1.0 - self.a) * self.x1
        self.x1 = self.a * self.x1 + self.q * n

    @property
    def value(self) -> float:
        return self.gain * (self.c1 * self.x1 + self.c2 * self.x2)


class DrydenWind:
    """The wind at the vehicle, world frame (x, y horizontal, z up), m/s, one sample per
    ``dt_s``: the mean wind along ``direction_rad`` plus Dryden gusts (u along the mean wind,
    v across it, w vertical). Seeded by ``rng``; the same draws give the same wind."""

    def __init__(
        self,
        level: WindLevel,
        dt_s: float,
        rng: np.random.Generator,
        direction_rad: float = 0.0,
        height_m: float = 2.0,
    ) -> None:
        if not dt_s > 0:
            raise WindConfigError(f"the wind's time step must be positive, got {dt_s} s")
        self.level = level
        self.direction_rad = direction_rad
        self._rng = rng
        airspeed = max(MIN_AIRSPEED_MPS, level.mean_mps)
        l_uv, l_w = scale_lengths_m(height_m)
        sigma = level.turbulence_sigma_mps
        sigma_w = sigma * vertical_intensity_ratio(height_m)
        self.time_constants_s = (l_uv / airspeed, l_uv / airspeed, l_w / airspeed)
        self._u = _FirstOrder(sigma, l_uv / airspeed, dt_s)
        self._v = _DrydenTransverse(sigma, l_uv / airspeed, dt_s)
        self._w = _DrydenTransverse(sigma_w, l_w / airspeed, dt_s)
        n = rng.normal(size=5)
        self._u.start(sigma, float(n[0]))
        self._v.start(float(n[1]), float(n[2]))
        self._w.start(float(n[3]), float(n[4]))
        self._c, self._s = math.cos(direction_rad), math.sin(direction_rad)

    def step(self) -> tuple[float, float, float]:
        """The next sample of the wind, world frame, m/s."""
        if self.level.calm:
            return (0.0, 0.0, 0.0)
        n = self._rng.normal(size=3)
        self._u.step(float(n[0]))
        self._v.step(float(n[1]))
        self._w.step(float(n[2]))
        return self.now()

    def now(self) -> tuple[float, float, float]:
        """The wind as it blows now (the last sample, or the stationary draw it starts
        from), world frame, m/s; draws nothing."""
        if self.level.calm:
            return (0.0, 0.0, 0.0)
        u = self.level.mean_mps + self._u.value
        v, w = self._v.value, self._w.value
        return (self._c * u - self._s * v, self._s * u + self._c * v, w)

    def samples(self, n: int) -> Array:
        """``n`` successive samples, (n, 3)."""
        return np.array([self.step() for _ in range(n)], np.float64).reshape(n, 3)

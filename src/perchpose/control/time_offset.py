"""The camera-to-vehicle time offset, estimated online from the motion both see.

A frame's stamp says when it was captured only as well as its source knows: a live source
stamps the grab less a camera latency the user measured, and that measure is off by some
milliseconds (more where it was never measured). The target does not move, so the target's
position in the vehicle's world frame, placed from each fix with the vehicle's attitude and
odometry at the frame's capture time, is the same for every frame. Placed at the wrong time,
every roll, pitch and sway of the vehicle between the true capture and the stamp moves it:
the placed positions scatter with the vehicle's motion. The offset is the one that makes them
stillest, as visual-inertial systems calibrate the time between their camera and their IMU
online (the camera's time offset as one more unknown that the motion makes observable).

Over a sliding window of fixes (``window_s``), for offsets on a grid over
``[-max_offset_s, max_offset_s]`` (``grid_step_s``; searched coarse, then fine around the
coarse least), each fix's target is placed in the world at ``stamp + offset``, from the
attitude and the odometry's position there (the vehicle's samples smoothed over
``smooth_s``, then interpolated). What the offset cannot cause is fitted out by least
squares: a fixed point drifting along a straight line per axis (the odometry's slow drift),
a scale error of the fixes (the calibration's focal length, the print's size) and a small
turn of the camera's mount; the scatter left is the cost. A parabola through the fine grid's
lowest point and its neighbours gives the estimate. Its spread is the Newey-West sandwich
of the fixes' scores (each residual times its slope in the offset), which takes neither the
fixes' noise as equal nor as independent from one frame to the next. With little motion the
cost is flat and the spread wide.

``offset_s`` is the true capture time minus the stamp: the capture time is ``stamp +
offset_s``. The vehicle's samples are kept at the time they describe (their age removed), so
the offset is the camera's against the vehicle's state estimate.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from perchpose.errors import ControllerConfigError, require_non_negative, require_positive

Array = NDArray[np.float64]


@dataclass(frozen=True)
class TimeOffsetSettings:
    """window_s : the fixes an estimate rests on (the newest's stamp back this far).
    max_offset_s : the largest offset searched, either way. grid_step_s : the search's step.
    min_fixes : fewer fixes in the window give no estimate. min_span_s : nor do fixes that
    span less time than this. every_fixes : an estimate is made once this many fixes came
    since the last one. trusted_sigma_s : the estimate corrects the stamps only while its
    spread is under this. smooth_s : the vehicle's samples are smoothed by a Gaussian kernel
    this wide before they are interpolated (their own noise, white from sample to sample,
    would otherwise pull the estimate towards offsets that fall between samples)."""

    window_s: float = 3.0
    max_offset_s: float = 0.15
    grid_step_s: float = 0.005
    min_fixes: int = 20
    min_span_s: float = 1.0
    every_fixes: int = 3
    trusted_sigma_s: float = 0.005
    smooth_s: float = 0.02

    def __post_init__(self) -> None:
        require_positive(
            self,
            ("window_s", "max_offset_s", "grid_step_s", "min_span_s", "trusted_sigma_s"),
            ControllerConfigError,
        )
        require_non_negative(self, ("smooth_s",), ControllerConfigError)
        if self.grid_step_s > self.max_offset_s:
            raise ControllerConfigError(
                f"grid_step_s ({self.grid_step_s}) must not exceed max_offset_s "
                f"({self.max_offset_s})"
            )
        if self.min_fixes < 8 or self.every_fixes < 1:
            raise ControllerConfigError(
                f"min_fixes must be >= 8 and every_fixes >= 1, got {self.min_fixes} and "
                f"{self.every_fixes}"
            )


@dataclass(frozen=True)
class TimeOffset:
    """An estimate: ``offset_s`` (true capture time minus stamp) with its standard deviation
    ``sigma_s``, from ``fixes`` fixes whose stamps span ``from_s`` to ``to_s``; made at
    ``t_s`` (the newest fix's stamp then)."""

    offset_s: float
    sigma_s: float
    fixes: int
    from_s: float
    to_s: float
    t_s: float

    def describe(self) -> str:
        """In words: ``frames captured 80 ms before their stamps (+- 1.5 ms, from 90 fixes)``."""
        ms = self.offset_s * 1000.0
        side = "before" if ms < 0.0 else "after"
        return (
            f"frames captured {abs(ms):.0f} ms {side} their stamps (+- {self.sigma_s * 1000.0:.1f} "
            f"ms, from {self.fixes} fixes)"
        )


class _Samples:
    """A time-ordered history of vector samples in a growing buffer, interpolated linearly."""

    def __init__(self, width: int) -> None:
        self.width = width
        self._t = np.empty(256)
        self._v = np.empty((256, width))
        self._start = 0
        self._end = 0
        self._version = 0  # counts the changes, for the smoothed samples' cache
        self._cache: tuple[tuple[int, float], Array] | None = None

    @property
    def times(self) -> Array:
        times: Array = self._t[self._start : self._end]
        return times

    def add(self, t_s: float, value: Array) -> None:
        v = np.asarray(value, np.float64).reshape(self.width)
        if not math.isfinite(t_s) or not np.all(np.isfinite(v)):
            return
        if self._end > self._start and t_s <= self._t[self._end - 1]:
            return  # out of order or repeated: the history stays strictly increasing
        if self._end == self._t.size:
            kept = self._end - self._start
            size = max(self._t.size, 2 * kept)
            t, values = np.empty(size), np.empty((size, self.width))
            t[:kept], values[:kept] = (
                self._t[self._start : self._end],
                self._v[self._start : self._end],
            )
            self._t, self._v, self._start, self._end = t, values, 0, kept
        self._t[self._end], self._v[self._end] = t_s, v
        self._end += 1
        self._version += 1

    def drop_before(self, t_s: float) -> None:
        """Forget the samples before ``t_s``, but one at or before it (to interpolate at it)."""
        i = int(np.searchsorted(self.times, t_s, side="right")) - 1
        if i > 0:
            self._start += i
            self._version += 1

    def _smoothed(self, smooth_s: float) -> Array:
        """The samples smoothed by a Gaussian kernel of ``smooth_s`` over the neighbours
        within three of it (kept until a sample comes or goes)."""
        key = (self._version, smooth_s)
        if self._cache is not None and self._cache[0] == key:
            return self._cache[1]
        times, values = self.times, self._v[self._start : self._end]
        if smooth_s > 0.0 and times.size > 1:
            gaps = np.diff(times)
            reach = min(MAX_NEIGHBOURS, int(math.ceil(3.0 * smooth_s / float(gaps.min()))))
            total = values.copy()
            weight = np.ones(times.size)
            for k in range(1, min(reach, times.size - 1) + 1):
                d = (times[k:] - times[:-k]) / smooth_s
                w = np.exp(-0.5 * d * d)
                total[k:] += w[:, None] * values[:-k]
                total[:-k] += w[:, None] * values[k:]
                weight[k:] += w
                weight[:-k] += w
            values = total / weight[:, None]
        self._cache = (key, values)
        return values

    def covers(self, from_s: float, to_s: float) -> bool:
        times = self.times
        return times.size >= 2 and times[0] <= from_s and to_s <= times[-1]

    def at(self, t_s: Array, smooth_s: float) -> Array:
        """The samples at times ``t_s`` (any shape), shape ``t_s.shape + (width,)``: the
        history smoothed by a Gaussian kernel of ``smooth_s`` (0: as it is), then
        interpolated linearly. Unsmoothed, a sample's own noise would be halved midway between
        two samples and whole at each: the scatter would then depend on where the offset puts
        the fixes among the samples, not only on the offset."""
        times = self.times
        values = self._smoothed(smooth_s)
        flat = t_s.ravel()
        out = np.empty((flat.size, self.width))
        for j in range(self.width):
            out[:, j] = np.interp(flat, times, values[:, j])
        return out.reshape(*t_s.shape, self.width)


class TimeOffsetEstimator:
    """Estimates the offset from fixes of the target and the vehicle's attitude and odometry.

    ``attitude`` and ``position`` take the vehicle's samples at the times they describe;
    ``fix`` takes each measured frame's stamp and the target's position in the body frame,
    and returns a new estimate when one was made (``latest`` keeps the last)."""

    def __init__(self, settings: TimeOffsetSettings | None = None) -> None:
        self.settings = settings or TimeOffsetSettings()
        s = self.settings
        self._attitudes = _Samples(9)
        self._positions = _Samples(3)
        self._fixes: deque[tuple[float, Array]] = deque()
        self._since = 0
        self.latest: TimeOffset | None = None
        steps = int(round(s.max_offset_s / s.grid_step_s))
        self._grid_s = np.arange(-steps, steps + 1, dtype=np.float64) * s.grid_step_s

    @property
    def correction_s(self) -> float:
        """What to add to a stamp for the capture time: the latest estimate while it is
        trusted (spread under ``trusted_sigma_s``), else 0."""
        e = self.latest
        if e is None or not e.sigma_s < self.settings.trusted_sigma_s:
            return 0.0
        return e.offset_s

    def attitude(self, t_s: float, R_world_body: Array) -> None:
        self._attitudes.add(t_s, np.asarray(R_world_body, np.float64).reshape(9))

    def position(self, t_s: float, p_m: Array) -> None:
        self._positions.add(t_s, np.asarray(p_m, np.float64))

    def fix(self, t_s: float, p_body_target_m: Array) -> TimeOffset | None:
        """A measured frame stamped ``t_s``: the target's position in the body frame (m).
        The new estimate, when this fix made one."""
        s = self.settings
        p = np.asarray(p_body_target_m, np.float64)
        if not math.isfinite(t_s) or not np.all(np.isfinite(p)):
            return None
        if self._fixes and t_s <= self._fixes[-1][0]:
            return None
        self._fixes.append((t_s, p))
        oldest_s = t_s - s.window_s  # no fix before this is used again
        while self._fixes[0][0] < oldest_s:
            self._fixes.popleft()
        # the samples reach back past the oldest fix's search, and the smoothing's beyond it
        self._attitudes.drop_before(oldest_s - 2.0 * s.max_offset_s)
        self._positions.drop_before(oldest_s - 2.0 * s.max_offset_s)
        self._since += 1
        if self._since < s.every_fixes:
            return None
        self._since = 0
        estimate = self._estimate(t_s)
        if estimate is not None:
            self.latest = estimate
        return estimate

    def _usable(self) -> list[tuple[float, Array]]:
        """The window's fixes whose whole search range the vehicle's samples cover."""
        s = self.settings
        m = s.max_offset_s + 3.0 * s.smooth_s  # the smoothing is one-sided at the ends
        return [
            (t, p)
            for t, p in self._fixes
            if self._attitudes.covers(t - m, t + m) and self._positions.covers(t - m, t + m)
        ]

    def _estimate(self, newest_s: float) -> TimeOffset | None:
        s = self.settings
        fixes = self._usable()
        if len(fixes) < s.min_fixes:
            return None
        t = np.array([f[0] for f in fixes])
        if t[-1] - t[0] < s.min_span_s:
            return None
        b = np.stack([f[1] for f in fixes])  # (N, 3) body frame
        # the cost on a coarse grid (every third offset), then on the fine one around its least
        coarse = self._grid_s[::COARSE]
        c_cost, _ = self._cost(t, b, coarse)
        i = int(np.argmin(c_cost))
        j0 = max(0, i * COARSE - COARSE)
        grid = self._grid_s[j0 : i * COARSE + COARSE + 1]
        cost, residuals = self._cost(t, b, grid)
        j = int(np.argmin(cost))
        if j0 + j in (0, self._grid_s.size - 1) or j in (0, grid.size - 1):
            return None  # at the search's edge: no minimum inside it
        h = s.grid_step_s
        lower, mid, upper = float(cost[j - 1]), float(cost[j]), float(cost[j + 1])
        bend = lower - 2.0 * mid + upper
        if not bend > 0.0:
            return None
        shift = 0.5 * (lower - upper) / bend  # in grid steps, within (-0.5, 0.5)
        offset = float(grid[j]) + shift * h
        # each fix's residual and its slope in the offset, at the estimate
        slope = (residuals[:, j + 1, :] - residuals[:, j - 1, :]) / (2.0 * h)
        at = residuals[:, j, :] + shift * h * slope
        sigma = _hac_sigma(np.einsum("ni,ni->n", slope, at), float(np.sum(slope * slope)))
        n = len(fixes)
        return TimeOffset(offset, sigma, n, float(t[0]), float(t[-1]), newest_s)

    def _cost(self, t: Array, b: Array, offsets: Array) -> tuple[Array, Array]:
        """The unexplained scatter of the fixes placed at each offset, and its residuals
        (N, G, 3)."""
        q = t[:, None] + offsets[None, :]  # (N, G)
        smooth = self.settings.smooth_s
        R = self._attitudes.at(q, smooth).reshape(*q.shape, 3, 3)
        p = self._positions.at(q, smooth)
        placed = p + (R @ b[:, None, :, None])[..., 0]  # (N, G, 3) world frame
        residuals = _unexplained(t, placed, R, b)
        return np.einsum("ngi,ngi->g", residuals, residuals), residuals


COARSE = 3  # the coarse search's step, in grid steps
MAX_NEIGHBOURS = 64  # the most samples either side the smoothing reaches


def _unexplained(t_s: Array, placed: Array, R: Array, b: Array) -> Array:
    """What of the placed positions (N, G, 3) no nuisance explains, for each offset G: a
    fixed point and a straight-line drift in time per axis (the odometry's slow drift; a
    higher degree takes the approach's own motion for drift), a scale error of the fixes
    (``eps * R b``: the calibration's focal length, the print's size) and a small turn of the
    camera's mount (``R (e x b)``), fitted by least squares."""
    n, g, _ = placed.shape
    drift = np.polynomial.legendre.legvander(_unit(t_s), 1)  # (N, 2)
    k = drift.shape[1]
    count = 3 * k + 4
    X = np.zeros((g, n, 3, count))
    for axis in range(3):
        X[:, :, axis, axis * k : (axis + 1) * k] = drift[None]
    Rg = R.transpose(1, 0, 2, 3)  # (G, N, 3, 3)
    X[..., 3 * k] = (Rg @ b[None, :, :, None])[..., 0]
    # R (e x b) = -R [b]x e: the columns of -R [b]x
    skew = np.zeros((n, 3, 3))
    skew[:, 0, 1], skew[:, 0, 2] = -b[:, 2], b[:, 1]
    skew[:, 1, 0], skew[:, 1, 2] = b[:, 2], -b[:, 0]
    skew[:, 2, 0], skew[:, 2, 1] = -b[:, 1], b[:, 0]
    X[..., 3 * k + 1 :] = -(Rg @ skew[None])
    A = X.reshape(g, 3 * n, count)
    At = A.transpose(0, 2, 1)
    y = placed.transpose(1, 0, 2).reshape(g, 3 * n, 1)
    coefficients = np.linalg.solve(At @ A + 1e-12 * np.eye(count), At @ y)
    r = y - A @ coefficients
    out: Array = r.reshape(g, n, 3).transpose(1, 0, 2)
    return out


def _unit(t_s: Array) -> Array:
    """Times mapped onto [-1, 1] over their span."""
    low, high = float(t_s.min()), float(t_s.max())
    unit: Array = (2.0 * t_s - (low + high)) / max(high - low, 1e-9)
    return unit


def _hac_sigma(scores: Array, information: float) -> float:
    """The offset's standard deviation from each fix's score (its residual times the
    residual's slope in the offset) and the information (the slopes' sum of squares): the
    Newey-West sandwich, which neither takes the fixes' noise as equal (a frame later than
    the rest scatters more where the vehicle moves fast) nor as independent from one frame
    to the next (Bartlett weights over ``lags`` frames)."""
    n = scores.size
    if not information > 0.0 or n < 2:
        return math.inf
    lags = max(1, int(4.0 * (n / 100.0) ** (2.0 / 9.0)))
    meat = float(scores @ scores)
    for lag in range(1, min(lags, n - 1) + 1):
        meat += 2.0 * (1.0 - lag / (lags + 1.0)) * float(scores[lag:] @ scores[:-lag])
    return math.sqrt(max(meat, 0.0)) / information

"""The horizontal velocity error of an optical-flow deck's odometry, as its Kalman filter
leaves it.

A Crazyflie with a Flow deck v2 measures its horizontal velocity with a PMW3901 optical-flow
sensor looking down (a 35 x 35 pixel window over a 42 degree aperture, read at 100 Hz) and its
height with a VL53L1x time-of-flight range sensor. The firmware's flow model (``mm_flow.c``)
predicts the pixels a sample counts as ``dt * Npix / thetapix * (v_body / h - omega)``: the
flow is angular, so one pixel of noise is a velocity error proportional to the height ``h``,
and the body's own roll and pitch rates are taken out with the gyro. The Kalman filter weighs
each flow sample against its prediction from the accelerometer; in steady state that is a
first-order low-pass of the flow's error with a time constant of a tenth of a second or so
(``smoothing_s``): the estimate's error is **correlated over that time**, not white, and the
position, which integrates it, drifts.

What this model puts into each 10 ms flow sample, per body axis (then low-passed):

- pixel noise: ``pixel_noise_px`` per sample over a well-textured floor, 0.4 times the 0.2 px
  the firmware's filter assumes (``stdDevX`` 2.0 times ``FLOW_RESOLUTION`` 0.1), so that at 1 m
  with a 0.15 s time constant the estimate's velocity error is about 3 cm/s; it grows with the
  height, since a pixel is ``h * 42 deg / 35`` of floor;
- yaw: a yaw rate turns the window about its centre by ``omega_z * dt`` per sample, smearing
  its edge pixels (17 from the centre) by ``17 * omega_z * dt`` pixels; ``rotation_blur`` of
  that smear is taken as extra noise of the block match (a stated assumption: the PMW3901's
  datasheet gives no figure under rotation);
- scale: a velocity off by a share ``scale_error`` at most (half-width): the firmware's
  aperture constant ``2 sin(21 deg)`` = 0.7167 rad against the lens's 42 deg = 0.7330 rad is
  2.2 % by itself, the lens's tolerance and the VL53L1x's ranging error (a few percent at a
  few metres over a grey floor, from its datasheet's ranging accuracy) add to it;
- gyro mismatch: a share ``gyro_mismatch`` (half-width) of the rotational flow is left after
  the gyro's compensation (the two sensors' scales and their sample times differ): a velocity
  error of that share of ``h * omega_xy``.

The vertical axis is not the deck's flow but its range: it is left to the odometry's white
noise (``OdometryModel``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from perchpose.errors import SensingConfigError, require_non_negative

Array = NDArray[np.float64]

FLOW_HZ = 100.0  # the Flow deck v2 reads the PMW3901 at this rate
WINDOW_PX = 35.0  # the PMW3901's window, pixels across (the firmware's Npix)
APERTURE_RAD = math.radians(42.0)  # the PMW3901's field of view
EDGE_PX = WINDOW_PX / 2.0  # the window's edge pixels, from its centre


@dataclass(frozen=True)
class FlowDeck:
    """Spreads of a flow deck's horizontal odometry error (the module's text says where
    each comes from). pixel_noise_px : per flow sample. smoothing_s : range of the Kalman
    filter's time constant on the flow, drawn per run. scale_error, gyro_mismatch : half-widths
    of the velocity's scale error and of the share of rotational flow left, drawn per run.
    rotation_blur : the share of the window's smear under yaw that is noise. min_height_m : the
    height the firmware's model never goes under (its 0.1 m saturation)."""

    pixel_noise_px: float = 0.08
    smoothing_s: tuple[float, float] = (0.05, 0.25)
    scale_error: float = 0.03
    gyro_mismatch: float = 0.03
    rotation_blur: float = 0.25
    min_height_m: float = 0.1

    def __post_init__(self) -> None:
        spreads = ("pixel_noise_px", "scale_error", "gyro_mismatch", "rotation_blur")
        require_non_negative(self, spreads, SensingConfigError)
        low, high = self.smoothing_s
        if not (math.isfinite(low) and math.isfinite(high) and 0 < low <= high):
            raise SensingConfigError(f"smoothing_s must be 0 < low <= high, got {low}, {high}")
        if not (math.isfinite(self.min_height_m) and self.min_height_m > 0):
            raise SensingConfigError(f"min_height_m must be positive, got {self.min_height_m}")

    def velocity_per_pixel(self, height_m: float) -> float:
        """The horizontal speed (m/s) that one pixel per flow sample means at ``height_m``."""
        return max(self.min_height_m, height_m) * APERTURE_RAD / WINDOW_PX * FLOW_HZ


class FlowDeckError:
    """One run's flow-deck odometry error: its draws (``smoothing_s``, ``scale``,
    ``gyro_share``) and its state, advanced flow sample by flow sample."""

    def __init__(self, deck: FlowDeck, rng: np.random.Generator) -> None:
        self.deck = deck
        self._rng = rng
        self.smoothing_s = float(rng.uniform(*deck.smoothing_s))
        self.scale = float(rng.uniform(-deck.scale_error, deck.scale_error))
        self.gyro_share: Array = rng.uniform(-deck.gyro_mismatch, deck.gyro_mismatch, 2)
        self.e_body_mps = np.zeros(2)  # the estimate's error along the body's x and y
        self._pending_s = 0.0

    def advance(
        self,
        dt_s: float,
        height_m: float,
        v_world_mps: Array,
        R_world_body: Array,
        omega_rad_s: Array,
    ) -> Array:
        """Advance ``dt_s`` with the vehicle's true state; the estimate's horizontal velocity
        error now, in the world frame (z 0)."""
        self._pending_s += dt_s
        period = 1.0 / FLOW_HZ
        if self._pending_s >= period:
            R = np.asarray(R_world_body, np.float64)
            v_body = R.T @ np.asarray(v_world_mps, np.float64)
            w = np.asarray(omega_rad_s, np.float64)
            h = max(self.deck.min_height_m, height_m)
            per_px = self.deck.velocity_per_pixel(h)
            smear_px = EDGE_PX * abs(float(w[2])) * period
            sigma_px = math.hypot(self.deck.pixel_noise_px, self.deck.rotation_blur * smear_px)
            rotational = h * np.array([w[1], -w[0]])
            alpha = min(1.0, period / self.smoothing_s)
            while self._pending_s >= period:
                self._pending_s -= period
                flow_error = (
                    per_px * sigma_px * self._rng.normal(size=2)
                    + self.scale * v_body[:2]
                    + self.gyro_share * rotational
                )
                self.e_body_mps = self.e_body_mps + alpha * (flow_error - self.e_body_mps)
        e_world: Array = np.asarray(R_world_body, np.float64)[:, :2] @ self.e_body_mps
        e_world[2] = 0.0
        return e_world

"""The aerodynamic push the accelerometer measures, made fit to cancel: clamped and
low-passed over the propellers' vibration. The controller cancels it as a velocity offset
(``PerchingController``), the pilot's own velocity loop as a lean
(``control.attitude_command``)."""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from perchpose.geometry import clip_norm

Array = NDArray[np.float64]


class PushFilter:
    """The push (world x and y, m/s^2) at most ``max_mps2`` long, low-passed over
    ``filter_s`` (0: as it comes); none where ``feedforward`` is off or the sample is missing
    or not finite (the filter then starts again from none)."""

    def __init__(self, feedforward: bool, filter_s: float, max_mps2: float) -> None:
        self.feedforward = feedforward
        self.filter_s = filter_s
        self.max_mps2 = max_mps2
        self.value = np.zeros(2)

    def update(self, push_mps2: ArrayLike | None, dt_s: float) -> Array:
        """Take a sample ``dt_s`` after the last (any components past x and y must be finite
        too, and count for nothing else) and give the filtered push."""
        if not self.feedforward or push_mps2 is None:
            self.value = np.zeros(2)
            return self.value
        measured = np.asarray(push_mps2, np.float64).reshape(-1)
        if not np.all(np.isfinite(measured)):
            self.value = np.zeros(2)
            return self.value
        xy = clip_norm(measured[:2], self.max_mps2)
        alpha = 1.0 if self.filter_s == 0 else 1.0 - math.exp(-dt_s / self.filter_s)
        self.value = self.value + alpha * (xy - self.value)
        return self.value

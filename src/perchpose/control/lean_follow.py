"""Does the vehicle fly the lean it is sent? A watch on attitude setpoints.

A vehicle sent attitude setpoints holds its own estimate of its attitude at the lean sent,
through an attitude loop that answers in a tenth or two of a second. Where the two part for
longer, the vehicle is not flying what the pilot sends: most dangerously, it takes one angle
with the other sign (the Crazyflie's legacy pitch, positive nose up, which its client
libraries negate and which Bitcraze means to take out of its stack; a roll sign flipped in
some client). The pilot's velocity loop then drives the vehicle away from the
target at the largest lean it may ask, faster the further it goes: in a simulated strong-wind
run with the pitch flipped, the vehicle's pitch stood 20 deg from the lean sent 0.4 s after the
take-over, and it crashed within two seconds.

The watch compares the vehicle's own roll and pitch with the lean sent as a first-order loop of
``response_s`` would fly it, over the last ``window_s``: an angle is not followed where the
vehicle's stood on average more than ``max_error_deg`` from it and went against it (the slope of
the vehicle's angle on the one flown, fitted over the window, under ``AGAINST_SLOPE``) while the
lean sent moved enough to tell (its spread over ``MIN_SPREAD_DEG``). A vehicle that merely does
not move, held by the plate's rim or the floor whatever lean is asked, is not judged (a slope
near 0: 0.2 and -0.1 in the two such strong-wind runs of 32 traced on the Crazyflie firmware's
PID and Kalman filter, where a threshold on the error alone judged both); in flight the error
stays small (the largest held for 0.3 s: 3.2 deg in the other 30, 2.8 in 20 moderate-wind runs,
2.3 in 15 strong-wind runs on the model's loops); a vehicle the plate is known to hold (within
the magnet's reach) is not watched at all. With the pitch flipped the watch judged 0.5 s after
the take-over in the runs traced.
"""

from __future__ import annotations

import math
from collections import deque

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]

AXES = ("roll", "pitch")
AGAINST_SLOPE = -0.5  # the vehicle's angle on the angle flown: 1 followed, 0 still, -1 flipped
MIN_SPREAD_DEG = 2.0  # the flown angle's spread (standard deviation) over the window


class LeanFollowWatch:
    """``update`` with each attitude setpoint sent; ``broken`` the first angle the vehicle did
    not follow (None while it follows)."""

    def __init__(self, response_s: float, window_s: float, max_error_deg: float) -> None:
        self.response_s = response_s
        self.window_s = window_s
        self.max_error_deg = max_error_deg
        self.broken: str | None = None
        self.detail = ""
        self._t_s: float | None = None
        self._flown = np.zeros(2)
        self._sent = np.zeros(2)
        # (t_s, the angles flown, the vehicle's own), degrees, over the last window
        self._samples: deque[tuple[float, Array, Array]] = deque()

    def restart(self) -> None:
        """Watch afresh from the next setpoint (after setpoints of another kind, or the plate's
        touch): the vehicle's lean then is the loop's start."""
        self._t_s = None
        self._samples.clear()

    def update(
        self,
        t_s: float,
        sent_rad: tuple[float, float],
        own_rad: tuple[float, float],
        *,
        watch: bool = True,
    ) -> str | None:
        """Take the roll and pitch sent at ``t_s`` and the vehicle's own (rad, its estimate's,
        as the link reports them); ``watch`` False: the vehicle cannot follow (held by the
        plate), so nothing is judged and the watch starts again. Gives ``broken``."""
        if self.broken is not None:
            return self.broken
        sent, own = np.degrees(sent_rad), np.degrees(own_rad)
        if not watch or not (np.all(np.isfinite(sent)) and np.all(np.isfinite(own))):
            self.restart()
            return None
        if self._t_s is None:
            self._flown = own.copy()
        else:
            alpha = 1.0 - math.exp(-max(0.0, t_s - self._t_s) / self.response_s)
            self._flown = self._flown + alpha * (self._sent - self._flown)
        self._t_s, self._sent = t_s, sent
        self._samples.append((t_s, self._flown, own))
        while t_s - self._samples[0][0] > self.window_s:
            self._samples.popleft()
        if t_s - self._samples[0][0] < 0.9 * self.window_s:
            return None  # not yet a window's worth
        flown = np.array([f for _, f, _ in self._samples])
        owns = np.array([o for _, _, o in self._samples])
        spread = flown.std(axis=0)
        for axis in range(2):
            if spread[axis] < MIN_SPREAD_DEG:
                continue
            x, y = flown[:, axis] - flown[:, axis].mean(), owns[:, axis] - owns[:, axis].mean()
            slope = float(np.mean(x * y)) / float(spread[axis]) ** 2
            error = float(np.mean(np.abs(owns[:, axis] - flown[:, axis])))
            if slope < AGAINST_SLOPE and error > self.max_error_deg:
                self.broken = AXES[axis]
                self.detail = (
                    f"{AXES[axis]} sent {sent[axis]:+.0f} deg, the vehicle's "
                    f"{own[axis]:+.0f} deg; over {self.window_s:g} s {error:.0f} deg apart on "
                    f"average, turning {slope:+.1f} times the way sent"
                )
                break
        return self.broken

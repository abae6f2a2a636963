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
``response_s`` would fly it, in statistics weighted over the last ``window_s`` or so (each
sample's weight falling by e over it) since the watch began: an angle is not followed where the
vehicle's stood on average more than ``max_error_deg`` from it and went against it (the slope of
the vehicle's angle on the one flown, fitted with those weights, under ``AGAINST_SLOPE``) while
the angle flown moved enough to tell (its spread over ``MIN_SPREAD_DEG``). A vehicle that
merely does not move, held by the plate's rim or the floor whatever lean is asked, is not judged
(a slope near 0: 0.06 and -0.23 in the two such strong-wind runs of 32 traced on the Crazyflie
firmware's PID and Kalman filter, where a threshold on the error alone judged both); in flight
the error stays small (the largest held for 0.3 s: 3.2 deg in the other 30, 2.8 in 20
moderate-wind runs, 2.3 in 15 strong-wind runs on the model's loops); a vehicle the plate is
known to hold (within the magnet's reach) is not watched at all. With the pitch flipped the
watch judged 0.3 s after the take-over in the runs traced, before the lean asked had settled
at its largest (where, steady, it no longer tells a flipped angle from a held one).
"""

from __future__ import annotations

import math

import numpy as np

AXES = ("roll", "pitch")
AGAINST_SLOPE = -0.5  # the vehicle's angle on the angle flown: 1 followed, 0 still, -1 flipped
MIN_SPREAD_DEG = 2.0  # the flown angle's spread (weighted standard deviation)


class LeanFollowWatch:
    """``update`` with each attitude setpoint sent; ``broken`` the first angle the vehicle did
    not follow (None while it follows)."""

    def __init__(self, response_s: float, window_s: float, max_error_deg: float) -> None:
        self.response_s = response_s
        self.window_s = window_s
        self.max_error_deg = max_error_deg
        self.broken: str | None = None
        self.detail = ""
        self._t0_s: float | None = None  # when the watch began (None: it begins anew)
        self._t_s = 0.0
        self._flown = np.zeros(2)
        self._sent = np.zeros(2)
        # weighted sums: weight, flown, own, flown^2, flown*own, |own - flown| (degrees)
        self._sums = np.zeros((6, 2))

    def restart(self) -> None:
        """Watch afresh from the next setpoint (after setpoints of another kind, or the plate's
        touch): the vehicle's lean then is the loop's start."""
        self._t0_s = None

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
        if self._t0_s is None:
            self._t0_s, self._flown = t_s, own.copy()
            self._sums = np.zeros((6, 2))
        else:
            dt_s = max(0.0, t_s - self._t_s)
            self._flown = self._flown + (1.0 - math.exp(-dt_s / self.response_s)) * (
                self._sent - self._flown
            )
            self._sums *= math.exp(-dt_s / self.window_s)
        self._t_s, self._sent = t_s, sent
        x = self._flown
        self._sums += np.array([np.ones(2), x, own, x * x, x * own, np.abs(own - x)])
        if t_s - self._t0_s < self.window_s:
            return None  # not yet a window's worth
        weight, sx, sy, sxx, sxy, serr = self._sums
        mean_x, mean_y = sx / weight, sy / weight
        var_x = sxx / weight - mean_x * mean_x
        for axis in range(2):
            if not var_x[axis] >= MIN_SPREAD_DEG**2:
                continue
            slope = float((sxy[axis] / weight[axis] - mean_x[axis] * mean_y[axis]) / var_x[axis])
            error = float(serr[axis] / weight[axis])
            if slope < AGAINST_SLOPE and error > self.max_error_deg:
                self.broken = AXES[axis]
                self.detail = (
                    f"{AXES[axis]} sent {sent[axis]:+.0f} deg, the vehicle's "
                    f"{own[axis]:+.0f} deg; {error:.0f} deg apart on average over about "
                    f"{self.window_s:g} s, turning {slope:+.1f} times the way sent"
                )
                break
        return self.broken

"""The camera's fixes handed to the vehicle's own state estimator as an external position.

A vehicle's own estimator (the Crazyflie's Kalman filter on a Flow deck) flies its velocity
loop on a velocity whose error is correlated over a tenth of a second or more and, in wind,
biased (its model has no drag): the vehicle moves, its odometry does not see it, and only the
camera does, a latency later. The target does not move, so each fix says where the vehicle
is: the target's place in the odometry frame, anchored once from the first fixes, less the
vector the fix measured. Fused by the vehicle's filter (cflib's ``send_extpos``, what a
motion-capture system sends), that corrects the velocity where the vehicle's loop runs.

Each fix is the odometry's position now, moved by how far the target seems to have moved in
the odometry frame since it was anchored: ``p_now + (anchor - target_from_fix)``; the fix was
placed with the odometry's position at its capture time, so the latency does not enter. A fix
whose horizontal shift is larger than ``max_jump_m`` is not sent (an outlier); after
``reanchor_after`` of those in a row (the odometry drifted while the target was out of
sight), the target's place is anchored afresh.

The height is judged apart. The vehicle's estimator takes its height from a range sensor
looking at the floor, which the camera looking at the plate need not agree with: the
firmware's range model takes a tilted sensor's reading as the nearest edge of its cone (its
tilt less 7.5 deg), so a sensor that reads along its axis puts the estimate 3 % of the height
too high at 18 deg of tilt, 6 cm at 2 m, and the two part by that much in every strong gust.
Gated on all three axes, the fixes were all refused there, just under the plate where the
horizontal correction matters most, and the filter's velocity, uncorrected, drifted the
vehicle out of view (strong wind, 15 of 100 runs lost; 9 with the horizontal gate). A fix
whose height is further than ``max_height_jump_m`` from the estimate's carries the estimate's
own height (it corrects the horizontal position alone).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from perchpose.errors import ControllerConfigError

Array = NDArray[np.float64]


@dataclass(frozen=True)
class PositionFixSettings:
    """send : hand each measured fix to the vehicle's estimator where the link can.
    anchor_fixes : fixes averaged into the target's place before the first is sent.
    max_jump_m : a fix further than this horizontally from the vehicle's own estimate is not
    sent. max_height_jump_m : a fix further than this vertically carries the estimate's own
    height.
    reanchor_after : that many refused in a row anchor the target afresh. std_m : the spread
    the vehicle's filter is told a fix has (the Crazyflie's ``locSrv.extPosStdDev`` default)."""

    send: bool = True
    anchor_fixes: int = 10
    max_jump_m: float = 0.1
    max_height_jump_m: float = 0.3
    reanchor_after: int = 10
    std_m: float = 0.01

    def __post_init__(self) -> None:
        if self.anchor_fixes < 1 or self.reanchor_after < 1:
            raise ControllerConfigError("anchor_fixes and reanchor_after must be >= 1")
        if not (self.max_jump_m > 0 and self.max_height_jump_m >= 0 and self.std_m > 0):
            raise ControllerConfigError(
                "max_jump_m and std_m must be positive, max_height_jump_m not negative"
            )


class PositionFixes:
    """The vehicle's position from each fix, in its odometry frame (``fix``)."""

    def __init__(self, settings: PositionFixSettings | None = None) -> None:
        self.settings = settings or PositionFixSettings()
        self.anchor_m: Array | None = None
        self._first: list[Array] = []
        self._refused = 0
        self.sent = 0
        self.refused = 0

    def fix(self, target_odom_m: Array, p_now_m: Array) -> Array | None:
        """The vehicle's position now as a fix says it: ``target_odom_m`` is the target's
        place in the odometry frame from this fix (placed with the odometry at its capture),
        ``p_now_m`` the odometry's position now. None while anchoring or for an outlier."""
        s = self.settings
        target = np.asarray(target_odom_m, np.float64)
        if not (np.all(np.isfinite(target)) and np.all(np.isfinite(p_now_m))):
            return None
        if self.anchor_m is None:
            self._first.append(target)
            if len(self._first) >= s.anchor_fixes:
                self.anchor_m = np.mean(self._first, axis=0)
                self._first = []
            return None
        shift = self.anchor_m - target
        if abs(float(shift[2])) > s.max_height_jump_m:
            shift[2] = 0.0  # the horizontal position alone
        if float(np.linalg.norm(shift[:2])) > s.max_jump_m:
            self.refused += 1
            self._refused += 1
            if self._refused >= s.reanchor_after:
                self.anchor_m, self._refused = None, 0
            return None
        self._refused = 0
        self.sent += 1
        position: Array = np.asarray(p_now_m, np.float64) + shift
        return position

"""MAVLink TIMESYNC: this computer's clock against the autopilot's.

The protocol (common.xml, TIMESYNC id 111): a request carries ``tc1 = 0`` and the sender's
time in ``ts1`` (ns); the answer carries the responder's time in ``tc1`` and the request's
``ts1`` unchanged. Both sides may ask and both answer. From an answer, with ``rtt`` the round
trip on our clock, the autopilot's clock reads ``tc1 + rtt / 2`` when ours reads ``now``; the
offset is taken from the fastest round trip of the last few (a slow one carries queueing
delay, and half of it would bias the offset). An answer whose offset is more than ``JUMP_NS``
from the current one (clocks drift by parts per million, not by tenths of a second) means the
autopilot's clock restarted (a reboot): the answers before it are forgotten.

PX4 stamps a LANDING_TARGET with its own clock only through this offset: without it, a
message is stamped on arrival and the camera's latency goes uncompensated.
"""

from __future__ import annotations

import math
import time
from collections import deque
from collections.abc import Callable

WINDOW = 10  # answers the offset is chosen from
JUMP_NS = 200_000_000  # an offset this far from the last: the autopilot's clock restarted
PENDING = 16  # requests remembered while their answers are on the way
INT64_MAX = 2**63 - 1  # TIMESYNC's fields are int64


class TimeSync:
    """The offset from ``clock_ns`` (default ``time.monotonic_ns``) to the autopilot's clock.

    max_rtt_s : answers slower than this are not used (a link that queues them says little
    about the clocks)."""

    def __init__(
        self, max_rtt_s: float = 0.05, clock_ns: Callable[[], int] = time.monotonic_ns
    ) -> None:
        self.max_rtt_ns = int(max_rtt_s * 1e9)
        self.clock_ns = clock_ns
        self._pending: deque[int] = deque(maxlen=PENDING)
        self._samples: deque[tuple[int, int]] = deque(maxlen=WINDOW)  # (rtt, offset)
        self.answered = 0
        self.ignored = 0
        self.resets = 0

    def reset(self) -> None:
        """Forget every answer and pending request (the autopilot rebooted)."""
        self._pending.clear()
        self._samples.clear()
        self.resets += 1

    @property
    def offset_ns(self) -> int | None:
        """Autopilot time minus ours, ns (None before the first usable answer)."""
        if not self._samples:
            return None
        return min(self._samples)[1]

    @property
    def rtt_ns(self) -> int | None:
        """The round trip the offset was taken from."""
        return min(self._samples)[0] if self._samples else None

    def request(self) -> tuple[int, int]:
        """A request to send: (tc1, ts1)."""
        now = self.clock_ns()
        self._pending.append(now)
        return 0, now

    def handle(self, tc1: int, ts1: int) -> tuple[int, int] | None:
        """A received TIMESYNC: the answer to send back for a request, None for an answer
        (which updates the offset when it answers one of ours in time). Times are ns since
        each side's boot, so a negative one is not a time: it is neither answered nor used
        (``ignored`` counts them)."""
        now = self.clock_ns()
        if not (0 <= tc1 <= INT64_MAX and 0 <= ts1 <= INT64_MAX):
            self.ignored += 1
            return None
        if tc1 == 0:
            self.answered += 1
            return now, ts1
        if ts1 in self._pending:
            self._pending.remove(ts1)
            rtt = now - ts1
            if 0 <= rtt <= self.max_rtt_ns:
                offset = tc1 + rtt // 2 - now
                current = self.offset_ns
                if current is not None and abs(offset - current) > JUMP_NS:
                    self._samples.clear()
                    self.resets += 1
                self._samples.append((rtt, offset))
        return None

    def remote_usec(self, local_s: float) -> int | None:
        """A time on our clock (s, as ``time.monotonic()``) on the autopilot's, in us (None
        before the first usable answer, or for a time before the autopilot's boot)."""
        offset = self.offset_ns
        if offset is None or not math.isfinite(local_s):
            return None
        remote_us = (round(local_s * 1e9) + offset) // 1000
        return remote_us if remote_us >= 0 else None

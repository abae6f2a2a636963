"""The pilot's own clock on a vehicle link: a thread that ticks the pilot at a fixed rate from a
monotonic clock, so that its watchdogs and its landing run whether frames and samples come or
not."""

from __future__ import annotations

import threading

from perchpose.control.pilot import PerchingPilot


class PilotClock:
    """Ticks ``pilot`` every ``period_s`` (default its ``setpoint_period_s``) on a daemon
    thread until ``stop``. A tick is skipped when the pilot sent a command less than a period
    ago (a frame or an odometry sample ticked it already), so the vehicle hears the pilot at
    least once a period and not twice as often for it."""

    def __init__(self, pilot: PerchingPilot, period_s: float | None = None) -> None:
        self.pilot = pilot
        self.period_s = pilot.settings.setpoint_period_s if period_s is None else period_s
        self.ticks = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="perchpose-pilot", daemon=True)

    def start(self) -> PilotClock:
        self._thread.start()
        return self

    def _run(self) -> None:
        failed = False
        while not self._stop.wait(self.period_s):
            try:
                if self.pilot.tick_now(quiet_s=0.9 * self.period_s) is not None:
                    self.ticks += 1
            except Exception as exc:  # a link that failed mid-send: said once, ticking goes on
                if not failed:
                    self.pilot.report(f"pilot: a tick failed: {exc} (reported once)")
                failed = True

    def stop(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join()

    def __enter__(self) -> PilotClock:
        return self.start()

    def __exit__(self, *_exc: object) -> None:
        self.stop()

"""The sample gate: what a vehicle's attitude and position samples must be to be flown on."""

import math

import numpy as np

from perchpose.io.samples import SampleGate

STILL = np.zeros(3)


def _attitudes(
    gate: SampleGate, times_ms: list[int], now_s: list[float], roll: float = 0.0
) -> list[str | None]:
    return [gate.attitude(t, roll, 0.0, 0.0, n) for t, n in zip(times_ms, now_s, strict=True)]


def test_reversed_and_repeated_samples() -> None:
    gate = SampleGate()
    assert _attitudes(gate, [1000, 1020, 1040], [0.0, 0.02, 0.04]) == [None, None, None]
    assert gate.attitude(1030, 0.0, 0.0, 0.0, 0.05) == "out of order"  # reordered by the link
    assert gate.attitude(1040, 0.0, 0.0, 0.0, 0.06) is None  # a repeat is harmless
    assert gate.attitude(1060, 0.0, 0.0, 0.0, 0.07) is None
    assert gate.refused == {"out of order": 1}
    assert gate.reboots == 0


def test_implausible_samples() -> None:
    gate = SampleGate()
    assert gate.attitude(1000, 1e30, 0.0, 0.0, 0.0) == "implausible"  # cos(1e30) is a number
    assert gate.attitude(1000, math.radians(70.0), 0.0, 0.0, 0.0) == "implausible"
    assert gate.attitude(1000, 0.0, math.radians(-65.0), 0.0, 0.0) == "implausible"
    assert gate.attitude(1000, math.radians(40.0), 0.0, 0.0, 0.0) is None
    assert gate.attitude(1020, math.inf, 0.0, 0.0, 0.02) == "non-finite"
    assert gate.position(1000, np.array([1e38, 0.0, 0.0]), STILL, 0.0) == "implausible"
    assert gate.position(1000, np.zeros(3), np.array([0.0, 45.0, 0.0]), 0.0) == "implausible"
    assert gate.position(1000, np.array([0.0, 0.0, -1.0]), STILL, 0.0) is None
    # 3 m in 20 ms is 150 m/s: a jump no vehicle makes
    assert gate.position(1020, np.array([3.0, 0.0, -1.0]), STILL, 0.02) == "implausible"
    assert gate.position(1040, np.array([0.01, 0.0, -1.0]), STILL, 0.04) is None
    assert gate.refused == {"implausible": 6, "non-finite": 1}


def test_a_position_reset_is_taken_once_it_holds() -> None:
    """An estimator reset moves the position 50 m for good: refused while it may be a glitch,
    taken once it has held for ``reboot_confirm_s``."""
    gate = SampleGate()
    assert gate.position(0, np.zeros(3), STILL, 0.0) is None
    verdicts = [
        gate.position(20 * k, np.array([50.0, 0.0, 0.0]), STILL, 0.02 * k) for k in range(1, 40)
    ]
    first = verdicts.index(None)
    assert all(v == "implausible" for v in verdicts[:first])
    assert all(v is None for v in verdicts[first:])
    assert 0.4 <= 0.02 * (first + 1) <= 0.6


def test_a_replay_of_old_samples_is_refused_for_good() -> None:
    """The live stream at 1 s of boot time onwards, and in between a replay of samples 10 s
    older with 40 deg of roll: every replayed sample is refused, however long it goes on."""
    gate = SampleGate()
    verdicts = []
    for k in range(200):  # 4 s at 50 Hz, the live and replayed samples interleaved
        now = 0.02 * k
        assert gate.attitude(20_000 + 20 * k, 0.0, 0.0, 0.0, now) is None
        verdicts.append(gate.attitude(10_000 + 20 * k, math.radians(40.0), 0.0, 0.0, now + 0.01))
    assert set(verdicts) == {"out of order"}
    assert gate.reboots == 0


def test_a_reboot_is_followed_and_the_old_clock_refused() -> None:
    """The autopilot reboots: its clock restarts near zero. Refused while the old clock may
    still be running, then taken as a reboot (said through ``on_reboot``); a late sample of
    the old clock is refused after it."""
    said: list[str] = []
    gate = SampleGate(on_reboot=said.append)
    for k in range(50):
        assert gate.attitude(600_000 + 20 * k, 0.0, 0.0, 0.0, 0.02 * k) is None
        assert gate.position(600_000 + 20 * k, np.zeros(3), STILL, 0.02 * k) is None
    verdicts = [gate.attitude(3_000 + 20 * k, 0.0, 0.0, 0.0, 1.0 + 0.02 * k) for k in range(50)]
    first = verdicts.index(None)
    assert set(verdicts[:first]) == {"out of order"}
    assert all(v is None for v in verdicts[first:])
    assert 0.5 <= 0.02 * first <= 0.54
    assert gate.reboots == 1
    assert len(said) == 1
    assert "went back to" in said[0]
    assert gate.attitude(600_990, 0.0, 0.0, 0.0, 2.1) == "before reboot"
    assert gate.attitude(4_100, 0.0, 0.0, 0.0, 2.1) is None
    assert gate.position(600_990, np.zeros(3), STILL, 2.1) == "before reboot"
    assert gate.position(4_100, np.zeros(3), STILL, 2.1) is None
    # ten minutes on, the new clock passes where the old one stopped: still taken
    now = 2.1
    for t_ms in range(4_120, 700_000, 20):
        now += 0.02
        assert gate.attitude(t_ms, 0.0, 0.0, 0.0, now) is None

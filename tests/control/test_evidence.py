"""What the vehicle's own height says about contact: a vehicle the magnet holds against the
plate, against one in free air that follows what it is asked with a lag; and what its
accelerometer says: a held vehicle is rigid."""

import numpy as np

from perchpose.control.evidence import ContactDetector, HeldDetector, RigidDetector

DT_S = 0.02  # odometry at 50 Hz


def _fly(
    asked_mps: list[float], held: bool, lag_s: float = 0.2, noise_m: float = 0.0
) -> list[bool]:
    """A vehicle 1.95 m up asked ``asked_mps`` (one per sample), following them through a
    first-order lag, or held where it is; what ``HeldDetector`` says at each sample."""
    detector = HeldDetector(1.0, 0.02)
    rng = np.random.default_rng(0)
    z, vz = 1.95, 0.0
    said = []
    for i, asked in enumerate(asked_mps):
        if not held:
            vz += (asked - vz) * DT_S / lag_s
            z += vz * DT_S
        said.append(detector.touched(i * DT_S, z + float(rng.normal(0.0, noise_m)), asked))
    return said


def test_a_vehicle_held_against_what_it_is_asked_is_contact() -> None:
    said = _fly([-0.1] * 100, held=True, noise_m=0.002)
    assert not any(said[:49])  # not before a whole window
    assert said[-1]


def test_a_held_vehicle_asked_down_and_up_in_turn_is_contact_once_the_asking_adds_up() -> None:
    """Stepping down out of the capture cone and climbing again, unequally: the net asked
    motion over a second passes 4 cm."""
    asked = ([-0.1] * 10 + [0.05] * 5) * 10
    assert _fly(asked, held=True)[-1]


def test_a_free_vehicle_is_never_read_as_held() -> None:
    for lag_s in (0.1, 0.3, 0.5):
        assert not any(_fly([-0.1] * 150, held=False, lag_s=lag_s))
        asked = ([-0.1] * 10 + [0.05] * 5) * 10
        assert not any(_fly(asked, held=False, lag_s=lag_s))
        assert not any(_fly(([-0.1] * 8 + [0.1] * 8) * 10, held=False, lag_s=lag_s))


def test_a_vehicle_asked_to_hold_is_never_read_as_held() -> None:
    """Hovering still is what a hovering vehicle does: no evidence."""
    assert not any(_fly([0.0] * 150, held=True))
    assert not any(_fly(([-0.1] * 8 + [0.1] * 8) * 10, held=True))  # nothing asked on net


def test_a_gap_in_the_height_starts_the_window_again() -> None:
    detector = HeldDetector(1.0, 0.02)
    for i in range(40):
        assert not detector.touched(i * DT_S, 1.95, -0.1)
    assert not detector.touched(0.8, None, -0.1)
    assert not any(detector.touched(0.8 + i * DT_S, 1.95, -0.1) for i in range(1, 45))


def test_a_climb_that_stopped_rising_is_contact() -> None:
    detector = ContactDetector(0.3, 0.005)
    heights = [min(1.9 + 0.15 * i * DT_S, 1.95) for i in range(60)]  # the plate at 1.95 m
    said = [detector.touched(i * DT_S, h) for i, h in enumerate(heights)]
    assert not any(said[:30])  # still rising: 1.9 m to 1.95 m takes 0.33 s
    assert said[-1]


def test_a_held_vehicle_reads_held_through_a_centimetre_of_height_noise() -> None:
    """A Kalman filter's height on a range sensor 2 m up scatters by about a centimetre:
    the trend, not the spread, tells a held vehicle from a free one."""
    said = _fly([-0.1] * 150, held=True, noise_m=0.01)
    assert said[-1]
    for lag_s in (0.1, 0.3, 0.5):
        assert not any(_fly([-0.1] * 150, held=False, lag_s=lag_s, noise_m=0.01))


def test_a_vehicle_leaving_the_plate_as_a_descent_is_asked_is_not_held() -> None:
    """Held against the plate through a hover (nothing asked), it comes off as the descent
    is asked 0.6 s into the window and follows it: over the window its height rose and fell,
    a flat trend, and the asking adds up to 4 cm, but all of it in the second half (a traced
    strong-wind run whose motors were stopped 3 cm under the plate). Held through the
    descent too, it is contact once both halves of a window asked for it."""
    detector = HeldDetector(1.0, 0.02)
    said = []
    z = 1.95
    for i in range(50):  # the hover: pressed up 2 cm, then held there
        z = min(1.97, z + 0.002)
        said.append(detector.touched(i * DT_S, z, 0.0))
    for i in range(50, 70):  # the descent asked: it follows at 0.1 m/s
        z -= 0.1 * DT_S
        said.append(detector.touched(i * DT_S, z, -0.1))
    assert not any(said)
    held = _fly([0.0] * 50 + [-0.1] * 60, held=True)
    assert not any(held[:75])  # the first half of the window still the hover's
    assert held[-1]


def test_a_held_vehicle_whose_height_drifts_against_the_asking_is_contact() -> None:
    """Held against the plate, a Kalman filter's height drifts up while a descent is asked
    (it takes the thrust's lean against the plate for acceleration): 5 cm in 0.6 s in a
    traced run. Where the caller knows the vehicle was at the plate (``against``), that is
    contact. Without that knowledge it is not (a gust lifts a free vehicle against the
    asking too); nor is the same drift with a climb asked, or a vehicle following a
    descent."""

    def said(rate_mps: float, asked_mps: float, against: bool) -> list[bool]:
        detector = HeldDetector(0.6, 0.02)
        return [
            detector.touched(i * DT_S, 1.95 + rate_mps * i * DT_S, asked_mps, against=against)
            for i in range(40)
        ]

    drifting = said(0.08, -0.1, against=True)
    assert not any(drifting[:30])  # not before a whole window
    assert drifting[-1]
    assert not any(said(0.08, -0.1, against=False))
    assert not any(said(0.08, 0.1, against=True))
    assert not any(said(-0.08, -0.1, against=True))


def _rigid_said(spreads_mps2: list[float], repeats: int = 1) -> list[bool | None]:
    """``RigidDetector(0.3 s, 0.6 m/s^2)`` fed accelerometer samples at 100 Hz, each read
    ``repeats`` times (the pilot reads the link's latest sample on every tick), whose
    vertical specific force spreads ``spreads_mps2[i]`` (normal) about gravity; what it says
    after each new sample."""
    detector = RigidDetector(0.3, 0.6)
    rng = np.random.default_rng(1)
    said = []
    for i, spread in enumerate(spreads_mps2):
        f = [0.1, -0.2, 9.81 + float(rng.normal(0.0, spread))]
        for _ in range(repeats):
            detector.add(i * 0.01, f)
        said.append(detector.rigid(i * 0.01))
    return said


def test_a_vehicle_whose_accelerometer_reads_only_its_noise_is_rigid() -> None:
    said = _rigid_said([0.2] * 60)
    assert said[:3] == [None] * 3  # too few samples to say
    assert all(said[3:])


def test_a_vehicle_whose_thrust_changes_reach_the_accelerometer_is_not_rigid() -> None:
    """A vehicle in free air fighting gusts: its vertical specific force spreads 1.5 m/s^2
    (1.7 over 0.3 s in a traced strong-wind run beside the plate)."""
    said = _rigid_said([1.5] * 60)
    assert not any(said[10:])


def test_an_impact_leaves_the_rigid_window_after_its_length() -> None:
    """The catch's impact shakes the accelerometer for a tenth of a second (+-4 m/s^2 in
    turn); rigid again once it is older than the window (0.3 s), not before."""
    detector = RigidDetector(0.3, 0.6)
    rng = np.random.default_rng(2)
    said = []
    for i in range(80):
        shake = (4.0 if i % 2 else -4.0) if 20 <= i < 30 else 0.0
        detector.add(i * 0.01, [0.0, 0.0, 9.81 + shake + float(rng.normal(0.0, 0.2))])
        said.append(detector.rigid(i * 0.01))
    assert all(said[3:20])
    assert not any(said[21:59])  # the last shake (i = 29) is in the window until i = 59
    assert all(said[60:])


def test_a_sample_read_again_is_not_a_new_one() -> None:
    """Read ten times each, a noisy accelerometer's samples are no more rigid than once:
    repeats would shrink the spread measured."""
    assert _rigid_said([1.5] * 60, repeats=10) == _rigid_said([1.5] * 60)


def test_no_accelerometer_says_nothing() -> None:
    detector = RigidDetector(0.3, 0.6)
    for i in range(50):
        detector.add(i * 0.01, None)
        detector.add(i * 0.01, [0.0, 0.0, float("nan")])
    assert detector.rigid(0.5) is None

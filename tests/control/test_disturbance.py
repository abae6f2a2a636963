import numpy as np

from perchpose.control.disturbance import DisturbanceObserver

K_V = 3.0
DT = 1 / 30


def _fly(observer: DisturbanceObserver, push_mps2: np.ndarray, v_cmd: np.ndarray, seconds: float):
    """A first-order velocity loop with a push, the observer's offset added to the command."""
    v = np.zeros(3)
    for _ in range(int(seconds / DT)):
        v_sp = v_cmd + observer.offset_mps
        for _ in range(10):  # the vehicle between frames
            v = v + DT / 10 * (K_V * (v_sp - v) + push_mps2)
        observer.update(v_sp, v, DT)
    return v


def test_a_steady_push_is_cancelled() -> None:
    observer = DisturbanceObserver(K_V, 5.0, (0.6, 0.6, 0.3))
    push = np.array([0.3, -0.2, -0.4])  # m/s^2: wind and a tired battery
    v = _fly(observer, push, np.zeros(3), 4.0)
    # without the observer the vehicle would drift at push / k_v (0.1, -0.07, -0.13 m/s)
    np.testing.assert_allclose(v, 0.0, atol=2e-3)
    np.testing.assert_allclose(observer.offset_mps, -push / K_V, atol=2e-3)


def test_a_commanded_change_of_speed_is_not_a_disturbance() -> None:
    observer = DisturbanceObserver(K_V, 5.0, (0.6, 0.6, 0.3))
    v = np.zeros(3)
    largest = 0.0
    gap_integral = np.zeros(3)
    v_cmd = np.array([0.3, 0.0, 0.2])
    for _ in range(60):
        v_sp = v_cmd + observer.offset_mps
        for _ in range(10):
            v = v + DT / 10 * (K_V * (v_sp - v))
        observer.update(v_sp, v, DT)
        gap_integral += DT * (v_cmd - v)
        largest = max(largest, float(np.abs(observer.offset_mps).max()))
    # the loop's own lag is in the model; a plain integral of (command - velocity) at a gain
    # of 2 /s would have wound up to 0.3 / k_v * 2 = 0.2 m/s here
    assert 2.0 * float(np.abs(gap_integral).max()) > 0.15
    assert largest < 0.02


def test_the_offset_stays_within_its_clamp() -> None:
    observer = DisturbanceObserver(K_V, 5.0, (0.2, 0.2, 0.1))
    _fly(observer, np.array([3.0, -3.0, 3.0]), np.zeros(3), 3.0)
    offset = observer.offset_mps
    assert abs(offset[0]) <= 0.2 + 1e-12
    assert abs(offset[1]) <= 0.2 + 1e-12
    assert abs(offset[2]) <= 0.1 + 1e-12
    # anti-windup: once the push is gone the estimate comes back within a second
    _fly(observer, np.zeros(3), np.zeros(3), 1.0)
    assert np.abs(observer.offset_mps).max() < 0.05


def test_faster_poles_cancel_a_new_push_sooner() -> None:
    """Moving the poles keeps the estimates and changes how fast a new push is taken out:
    after 0.2 s of a sudden push the faster observer has left less of it uncancelled."""
    push = np.array([0.4, 0.0, 0.0])
    residual = {}
    for rate in (5.0, 12.0):
        observer = DisturbanceObserver(K_V, 2.0, (0.6, 0.6, 0.3))
        _fly(observer, np.zeros(3), np.zeros(3), 1.0)
        observer.rate = rate
        assert observer.l2 == rate * rate
        np.testing.assert_allclose(observer.l1, 2.0 * rate - K_V)
        _fly(observer, push, np.zeros(3), 0.2)
        residual[rate] = float(push[0] - observer.a_mps2[0])
    assert 0.0 <= residual[12.0] < 0.5 * residual[5.0]


def _fly_late(observer: DisturbanceObserver, delay_steps: int, told: bool) -> list[float]:
    """The loop at 100 Hz, its velocity reaching the observer ``delay_steps`` samples late,
    the observer ``told`` how late (or taking it as current); a gust pushes for 0.3 s. The
    velocity flown, sample by sample."""
    dt = 0.01
    v = np.zeros(3)
    sent: list[np.ndarray] = [np.zeros(3)] * (delay_steps + 1)
    flown = []
    for k in range(300):
        push = np.array([0.8, 0.0, 0.0]) if 50 <= k < 80 else np.zeros(3)
        v_sp = observer.offset_mps.copy()
        v = v + dt * (K_V * (v_sp - v) + push)
        sent.append(v.copy())
        late = sent[-1 - delay_steps]
        observer.update(v_sp, late, dt, delay_steps * dt if told else 0.0)
        flown.append(float(v[0]))
    return flown


def test_a_late_velocity_is_compared_with_the_estimate_of_its_moment() -> None:
    """30 ms late measurements at 100 Hz, an observer at the final climb's 18 rad/s: told how
    late they are, it lets a gust push the vehicle less far (peak speed 57 against 67 mm/s,
    drift 30 against 33 mm) and settles as well. (At 25 rad/s and this delay the comparison
    with a past estimate rings: the rate limits what it can take.)"""
    told = _fly_late(DisturbanceObserver(K_V, 18.0, (0.6, 0.6, 0.3)), 3, told=True)
    current = _fly_late(DisturbanceObserver(K_V, 18.0, (0.6, 0.6, 0.3)), 3, told=False)
    drift_told = float(np.sum(np.abs(told))) * 0.01  # metres flown off, summed
    drift_current = float(np.sum(np.abs(current))) * 0.01
    assert drift_told < 0.95 * drift_current
    assert max(told) < 0.9 * max(current)
    assert abs(told[-1]) < 1e-3


def _late_loop(
    observer: DisturbanceObserver, delay_s: float, seconds: float, axis: int = 0, gain: float = K_V
) -> float:
    """A first-order loop of ``gain`` that answers the setpoint sent ``delay_s`` ago,
    commanded a 0.3 m/s step along ``axis`` with the observer's offset added, the observer
    updated at 100 Hz (an odometry's rate); the largest offset the observer asked for."""
    dt = 0.01
    steps_late = round(delay_s / dt)
    sent = [np.zeros(3)] * (steps_late + 1)
    v = np.zeros(3)
    step = np.zeros(3)
    step[axis] = 0.3
    largest = 0.0
    for _ in range(int(seconds / dt)):
        v_sp = step + observer.offset_mps
        sent.append(v_sp)
        answered = sent[-1 - steps_late]
        for _ in range(10):
            v = v + dt / 10 * (gain * (answered - v))
        observer.update(v_sp, v, dt)
        largest = max(largest, float(np.abs(observer.offset_mps).max()))
    return largest


def test_a_late_answer_is_not_a_disturbance_when_the_delay_is_known() -> None:
    """A vehicle that answers 0.13 s late (a real attitude loop): told the delay, the observer
    asks for little; not told, it reads the lag as a push and offsets the setpoint by several
    times as much."""
    told = _late_loop(DisturbanceObserver(K_V, 12.0, (0.6, 0.6, 0.3), delay_s=0.13), 0.13, 3.0)
    blind = _late_loop(DisturbanceObserver(K_V, 12.0, (0.6, 0.6, 0.3)), 0.13, 3.0)
    assert told < 0.04
    assert blind > 4 * told


def test_the_vertical_loop_is_modelled_apart() -> None:
    """A vertical loop answers sooner than the horizontal one (thrust needs no tilt first):
    one of 5.5 /s, 0.02 s late, asked for a vertical step. Modelled as it is, the observer
    asks for little; modelled as the horizontal loop (4.3 /s, 0.1 s late), it reads the early
    answer as a disturbance and offsets the vertical setpoint by several times as much."""
    clamp = (0.6, 0.6, 0.3)
    apart = DisturbanceObserver(K_V, 12.0, clamp, 0.1, vertical_gain=5.5, vertical_delay_s=0.02)
    alike = DisturbanceObserver(K_V, 12.0, clamp, 0.1)
    modelled = _late_loop(apart, 0.02, 3.0, axis=2, gain=5.5)
    horizontal = _late_loop(alike, 0.02, 3.0, axis=2, gain=5.5)
    assert modelled < 0.04
    assert horizontal > 4 * modelled
    np.testing.assert_allclose(apart.gains, [K_V, K_V, 5.5])


def test_a_measured_push_is_a_known_input_not_cancelled_twice() -> None:
    """A push measured apart and cancelled through the setpoint (the accelerometer's): given
    to the observer as known, its own estimate stays near zero and the vehicle holds still;
    not given, the observer takes it for a disturbance too and the vehicle is pushed back the
    other way, the push cancelled twice over until the observer catches up."""
    push = np.array([1.2, -0.8, 0.0])
    for known in (True, False):
        observer = DisturbanceObserver(K_V, 5.0, (0.6, 0.6, 0.3))
        v = np.zeros(3)
        drift = 0.0
        for _ in range(int(2.0 / DT)):
            v_sp = observer.offset_mps - push / K_V
            for _ in range(10):
                v = v + DT / 10 * (K_V * (v_sp - v) + push)
            observer.update(v_sp, v, DT, known_mps2=push if known else None)
            drift = max(drift, float(np.abs(v).max()))
        if known:
            assert np.abs(observer.a_mps2).max() < 1e-9
            assert drift < 1e-9
        else:
            np.testing.assert_allclose(observer.a_mps2, push, atol=0.05)
            assert drift > 0.05

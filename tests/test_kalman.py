import math

import numpy as np
import pytest

from perchpose.kalman import H, KalmanSettings, MarkerTrack, PaperKalmanFilter, transition


def test_matrices_follow_the_paper() -> None:
    F = transition(0.1)
    assert F.shape == (8, 8)
    np.testing.assert_array_equal(np.diag(F), np.ones(8))
    assert [F[0, 1], F[2, 3], F[4, 5], F[6, 7]] == [0.1] * 4
    assert np.count_nonzero(F) == 12
    np.testing.assert_array_equal(np.flatnonzero(H.sum(axis=0)), [0, 2, 4, 6])
    s = KalmanSettings(k1=2e-5, k2=3e-6)
    kf = PaperKalmanFilter(np.zeros(4), s)
    np.testing.assert_array_equal(kf.R, 2e-5 * np.eye(4))
    np.testing.assert_array_equal(kf.Q, 3e-6 * np.eye(8))


def test_tracks_constant_velocity_and_keeps_covariance_symmetric() -> None:
    kf = PaperKalmanFilter(np.array([0.0, 0.0, 0.0, 1.0]), KalmanSettings())
    rng = np.random.default_rng(0)
    dt = 1 / 30
    for k in range(1, 120):
        t = k * dt
        kf.predict(dt)
        kf.update(np.array([0.2 * t, 0.1 * t, -0.05 * t, 1.0 - 0.3 * t]) + rng.normal(0, 1e-3, 4))
        np.testing.assert_allclose(kf.P, kf.P.T, atol=1e-15)
        assert np.all(np.linalg.eigvalsh(kf.P) > 0)
    np.testing.assert_allclose(kf.x[[1, 3, 5, 7]], [0.2, 0.1, -0.05, -0.3], atol=0.03)


def test_yaw_crosses_the_wrap_without_a_full_turn() -> None:
    kf = PaperKalmanFilter(np.array([math.radians(170), 0, 0, 1]), KalmanSettings())
    yaws = []
    for k in range(1, 40):
        kf.predict(1 / 30)
        true_yaw = math.radians(170 + k)  # crosses 180 at k = 10
        kf.update(np.array([math.remainder(true_yaw, 2 * math.pi), 0, 0, 1]))
        yaws.append(kf.x[0])
        err = math.remainder(kf.x[0] - true_yaw, 2 * math.pi)
        assert abs(math.degrees(err)) < 1.0
    assert all(-math.pi < y <= math.pi for y in yaws)


def test_coasting_decays_velocities_by_alpha() -> None:
    s = KalmanSettings(alpha=0.85)
    kf = PaperKalmanFilter(np.zeros(4), s)
    kf.x[[1, 3, 5, 7]] = [1.0, 2.0, 3.0, 4.0]
    kf.decay_velocities()
    np.testing.assert_allclose(kf.x[[1, 3, 5, 7]], [0.85, 1.7, 2.55, 3.4])


def test_track_survives_exactly_n_max_missed_frames() -> None:
    track = MarkerTrack(KalmanSettings(n_max=8))
    z = np.array([0.0, 0.0, 0.0, 1.0])
    for k in range(5):
        track.measured(z + np.array([0, 0, 0, -0.01 * k]), k / 30)
    alive = []
    for k in range(5, 15):
        track.missed_frame(k / 30)
        alive.append(track.alive)
    assert alive == [True] * 8 + [False, False]
    # seen again: a fresh filter starting at the new measurement
    track.measured(np.array([0.5, 0.1, 0.1, 0.5]), 15 / 30)
    assert track.alive
    assert track.missed == 0
    assert track.filter is not None
    np.testing.assert_allclose(track.filter.pose, [0.5, 0.1, 0.1, 0.5])
    np.testing.assert_array_equal(track.filter.x[[1, 3, 5, 7]], 0.0)


def test_coasting_moves_with_the_decaying_velocity() -> None:
    track = MarkerTrack(KalmanSettings())
    for k in range(60):
        track.measured(np.array([0.0, 0.3 * k / 30, 0.0, 1.0]), k / 30)
    assert track.filter is not None
    before = track.filter.x[2]
    v = track.filter.x[3]
    track.missed_frame(60 / 30)
    assert track.filter.x[2] - before == pytest.approx(0.85 * v / 30, rel=1e-9)


def test_bad_settings_are_rejected() -> None:
    with pytest.raises(ValueError, match="k1 and k2"):
        KalmanSettings(k1=0.0)
    with pytest.raises(ValueError, match="alpha"):
        KalmanSettings(alpha=1.5)

import math

import numpy as np
import pytest

from perchpose.filters.kalman import (
    PAPER_COAST_S,
    CovarianceFilterSettings,
    CovarianceTrack,
    H,
    KalmanSettings,
    MarkerFilters,
    MarkerPresence,
    MarkerTrack,
    PaperKalmanFilter,
    transition,
    white_acceleration_noise,
)


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


def test_track_is_dropped_when_its_measurement_is_too_old_whatever_the_frame_count() -> None:
    track = MarkerTrack(KalmanSettings())
    for k in range(31):
        track.measured(np.array([0.0, 0.0, 0.0, 0.8 - 0.3 * k / 30]), k / 30)
    track.missed_frame(6.0)  # the first frame after a 5 s camera stall
    assert not track.alive
    assert track.predicted_pose(6.0) is None
    assert track.age_s(6.0) == math.inf


def test_coasting_ends_at_the_time_limit() -> None:
    track = CovarianceTrack(CovarianceFilterSettings(n_max=100, max_coast_s=0.2))
    R = 1e-6 * np.eye(4)
    track.measured(np.array([0.0, 0.0, 0.0, 1.0]), R, 0.0)
    alive = []
    for k in range(1, 10):
        track.missed_frame(k * 0.05)
        alive.append(track.alive)
    assert alive == [True] * 4 + [False] * 5
    assert pytest.approx(8 / 30) == PAPER_COAST_S


def test_a_measurement_after_a_long_gap_starts_a_new_filter() -> None:
    track = MarkerTrack(KalmanSettings())
    for k in range(30):
        track.measured(np.array([0.0, 0.01 * k, 0.0, 1.0 - 0.01 * k]), k / 30)
    track.measured(np.array([0.3, 0.05, 0.05, 0.5]), 10.0)  # no frames at all for 9 s
    assert track.filter is not None
    np.testing.assert_allclose(track.filter.pose, [0.3, 0.05, 0.05, 0.5])
    np.testing.assert_array_equal(track.filter.x[[1, 3, 5, 7]], 0.0)


def test_covariance_track_weighs_measurements_by_their_covariance() -> None:
    """Two tracks see the same steps; the one told its measurements are noisier moves less,
    keeps the prior, innovation and innovation covariance of its last update, and its P stays
    symmetric and positive definite."""
    settings = CovarianceFilterSettings()
    precise, noisy = CovarianceTrack(settings), CovarianceTrack(settings)
    z0 = np.array([0.1, 0.0, 0.0, 1.0])
    precise.measured(z0, 1e-6 * np.eye(4), 0.0)
    noisy.measured(z0, 1e-6 * np.eye(4), 0.0)
    z1 = np.array([0.1, 0.01, 0.0, 1.0])
    precise.measured(z1, 1e-6 * np.eye(4), 1 / 30)
    noisy.measured(z1, 1e-2 * np.eye(4), 1 / 30)
    assert precise.filter is not None
    assert noisy.filter is not None
    assert precise.filter.pose[1] > noisy.filter.pose[1] > 0.0
    np.testing.assert_allclose(precise.filter.x_prior[[0, 2, 4, 6]], z0, atol=1e-12)
    np.testing.assert_allclose(precise.filter.y, z1 - z0, atol=1e-12)
    assert precise.filter.S[1, 1] > 1e-6
    for f in (precise.filter, noisy.filter):
        np.testing.assert_allclose(f.P, f.P.T, atol=1e-15)
        assert np.all(np.linalg.eigvalsh(f.P) > 0)


def test_actual_covariance_is_the_filters_when_the_noise_is_as_assumed() -> None:
    """Told the measurements' actual covariance is the one it assumes, the track's actual
    pose covariance is its own; without an actual covariance it has none."""
    R = np.diag([1e-5, 4e-6, 4e-6, 9e-6])
    told, untold = (
        CovarianceTrack(CovarianceFilterSettings()),
        CovarianceTrack(CovarianceFilterSettings()),
    )
    for k in range(20):
        z = np.array([0.1, 0.01 * k, 0.0, 1.0])
        told.measured(z, R, k / 30, R)
        untold.measured(z, R, k / 30)
    assert told.actual_pose_covariance is not None
    assert told.pose_covariance is not None
    np.testing.assert_allclose(told.actual_pose_covariance, told.pose_covariance, rtol=1e-12)
    assert untold.actual_pose_covariance is None


def test_actual_covariance_matches_the_errors_of_a_mistuned_filter() -> None:
    """A filter that assumes 20 times the measurements' actual variance, on motion drawn from
    its own white-acceleration model: its errors spread as the actual covariance says (within
    10 % in standard deviation over 400 seeded tracks), while its own covariance is far off."""
    settings = CovarianceFilterSettings()
    q = np.array([settings.q_yaw, settings.q_position, settings.q_position, settings.q_position])
    dt = 1 / 30
    R_actual = np.diag([1e-6, 2.5e-7, 2.5e-7, 1e-6])
    R_assumed = 20.0 * R_actual
    Q = white_acceleration_noise(dt, q)
    F = transition(dt)
    rng = np.random.default_rng(3)
    errors, actual, own = [], [], []
    for _ in range(400):
        track = CovarianceTrack(settings)
        x = np.zeros(8)
        x[6] = 1.0
        for k in range(40):
            if k:
                x = F @ x + rng.multivariate_normal(np.zeros(8), Q)
            z = H @ x + rng.multivariate_normal(np.zeros(4), R_actual)
            track.measured(z, R_assumed, k * dt, R_actual)
        assert track.pose is not None
        errors.append(track.pose - H @ x)
        actual.append(np.sqrt(np.diag(track.actual_pose_covariance)))
        own.append(np.sqrt(np.diag(track.pose_covariance)))
    spread = np.std(np.array(errors) / np.array(actual), axis=0)
    assert np.all(np.abs(spread - 1.0) < 0.1), spread
    assert np.all(np.std(np.array(errors) / np.array(own), axis=0) < 0.7)


def test_covariance_track_wraps_yaw_and_follows_constant_velocity() -> None:
    track = CovarianceTrack(CovarianceFilterSettings())
    R = np.diag([1e-6, 1e-6, 1e-6, 1e-6])
    for k in range(90):
        t = k / 30
        yaw = math.remainder(math.radians(170 + 30 * t), 2 * math.pi)  # crosses 180 deg
        z = np.array([yaw, 0.1 * t, 0.0, 1.0 - 0.2 * t])
        track.measured(z, R, t)
        assert track.filter is not None
        assert -math.pi < track.filter.x[0] <= math.pi
    assert track.filter is not None
    np.testing.assert_allclose(
        track.filter.x[[1, 3, 5, 7]], [math.radians(30), 0.1, 0.0, -0.2], atol=1e-3
    )


def test_bad_coasting_limit_is_rejected() -> None:
    with pytest.raises(ValueError, match="max_coast_s"):
        KalmanSettings(max_coast_s=0.0)
    with pytest.raises(ValueError, match="max_coast_s"):
        CovarianceFilterSettings(max_coast_s=-1.0)


def test_marker_filters_fuse_the_measured_markers_or_every_live_one() -> None:
    filters = MarkerFilters(3, KalmanSettings())
    z0, z1 = np.array([0.1, 0.0, 0.0, 1.0]), np.array([0.1, 0.01, 0.0, 1.0])
    filters.advance({0: z0, 1: z1}, 0.0)
    assert set(filters.contributing({0, 1})) == {0, 1}
    filters.advance({1: z1}, 1 / 30)
    assert set(filters.contributing({1})) == {1}  # marker 0 coasts but does not fuse
    filters.advance({}, 2 / 30)
    assert set(filters.contributing(set())) == {0, 1}  # nothing measured: every live filter
    assert filters.age_s({0, 1}, 2 / 30) == pytest.approx(1 / 30)
    predicted = filters.predicted_pose(2, 3 / 30)  # marker 2 never seen: another's prediction
    assert predicted is not None
    np.testing.assert_allclose(predicted[1:], z0[1:], atol=0.02)
    assert MarkerFilters(2, KalmanSettings()).predicted_pose(0, 0.0) is None


def test_marker_presence_follows_the_filters_rule_for_missed_frames() -> None:
    """Which markers a frame counts (measured ones, else those still tracked) is the same from
    ``MarkerPresence`` as from the per-marker filters, over random measurement patterns with
    gaps past ``n_max`` frames and past ``max_coast_s``."""
    rng = np.random.default_rng(3)
    settings = KalmanSettings(n_max=4, max_coast_s=0.2)
    filters = MarkerFilters(3, settings)
    presence = MarkerPresence(3, settings.n_max, settings.max_coast_s)
    t_s = 0.0
    counted: set[int] = set()
    for _ in range(600):
        t_s += float(rng.choice([1 / 30, 1 / 30, 0.09]))  # sometimes a late frame
        measured = {i for i in range(3) if rng.random() < 0.25}
        z = np.array([0.1, 0.0, 0.0, 0.5])
        filters.advance(dict.fromkeys(measured, z), t_s)
        presence.advance(measured, t_s)
        tracked = presence.tracked(measured)
        assert tracked == set(filters.contributing(measured))
        counted.add(len(tracked))
    assert counted == {0, 1, 2, 3}  # every case came up

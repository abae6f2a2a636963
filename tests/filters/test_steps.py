"""The compiled Kalman steps against the filter's equations written with numpy's matrices."""

import numpy as np
import pytest

from perchpose.filters import steps
from perchpose.filters.kalman import H, transition, white_acceleration_noise


def spd(rng: np.random.Generator, n: int) -> np.ndarray:
    A = rng.normal(size=(n, n))
    return A @ A.T + n * np.eye(n)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_each_step_is_the_matrix_equation(seed: int) -> None:
    rng = np.random.default_rng(seed)
    x, P, R = rng.normal(size=8), spd(rng, 8), spd(rng, 4)
    dt = rng.uniform(0.01, 0.2)
    Q = white_acceleration_noise(dt, rng.uniform(0.1, 1.0, 4))
    F = transition(dt)
    np.testing.assert_allclose(steps.propagated_state(x, dt), F @ x, rtol=0, atol=1e-12)
    np.testing.assert_allclose(steps.propagated_covariance(P, dt, Q), F @ P @ F.T + Q, atol=1e-12)
    S = steps.innovation_covariance(P, R)
    np.testing.assert_allclose(S, H @ P @ H.T + R, atol=1e-12)
    solved, K = steps.gain(P, S)
    assert solved
    np.testing.assert_allclose(K, np.linalg.solve(S, H @ P).T, atol=1e-12)
    y = rng.normal(size=4)
    np.testing.assert_allclose(steps.corrected_state(x, K, y), x + K @ y, atol=1e-12)
    I_KH = np.eye(8) - K @ H
    expected = I_KH @ P @ I_KH.T + K @ R @ K.T
    np.testing.assert_allclose(steps.joseph_covariance(P, K, R), expected, atol=1e-10)
    assert steps.mahalanobis2(y, S) == pytest.approx(float(y @ np.linalg.solve(S, y)), rel=1e-12)


def test_a_singular_innovation_covariance_is_said() -> None:
    S = np.zeros((4, 4))
    solved, _ = steps.gain(np.eye(8), S)
    assert not solved
    assert steps.mahalanobis2(np.ones(4), S) == np.inf

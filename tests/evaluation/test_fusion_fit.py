"""The sigma fits of evaluation.fusion_fit (closed-form least squares and the paper's LMS)."""

import math
from pathlib import Path

import numpy as np
import pytest

from perchpose.evaluation.fusion_fit import fit_sigma_least_squares, fit_sigma_lms


@pytest.mark.parametrize("true_sigma", [0.275, 0.5, 0.728, 0.9])
def test_both_fits_recover_a_known_sigma(true_sigma: float) -> None:
    # inner and outer share an error e; the outer has -(1 - s)/s of it... built so that
    # s * outer + (1 - s) * inner equals the truth plus small noise exactly when s = true_sigma
    rng = np.random.default_rng(1)
    truth = rng.uniform(-20, 20, 2000)
    common = rng.normal(0, 1.0, 2000)
    outer = truth + (1 - true_sigma) * common
    inner = truth - true_sigma * common
    noise = rng.normal(0, 0.01, 2000)
    ls = fit_sigma_least_squares(outer + noise, inner, truth)
    lms, passes = fit_sigma_lms(outer + noise, inner, truth)
    assert ls == pytest.approx(true_sigma, abs=0.01)
    assert lms == pytest.approx(ls, abs=0.01)
    assert passes < 200


def test_least_squares_is_the_variance_weighting_for_independent_errors() -> None:
    rng = np.random.default_rng(2)
    truth = rng.uniform(-5, 5, 20000)
    outer = truth + rng.normal(0, 0.3, truth.size)
    inner = truth + rng.normal(0, 0.6, truth.size)
    expected = 0.6**2 / (0.3**2 + 0.6**2)  # the inverse-variance weight of the outer marker
    assert fit_sigma_least_squares(outer, inner, truth) == pytest.approx(expected, abs=0.01)


def test_yaw_fit_works_across_the_wrap() -> None:
    rng = np.random.default_rng(3)
    truth = np.radians(rng.choice([179.0, -179.0, 178.5], 3000))
    outer = truth + np.radians(rng.normal(0, 0.5, truth.size))
    inner = truth + np.radians(rng.normal(0, 0.5, truth.size))
    wrap = lambda a: np.remainder(a + math.pi, 2 * math.pi) - math.pi  # noqa: E731
    ls = fit_sigma_least_squares(wrap(outer), wrap(inner), truth, circular=True)
    lms, _ = fit_sigma_lms(wrap(outer), wrap(inner), truth, circular=True)
    assert ls == pytest.approx(0.5, abs=0.03)
    assert lms == pytest.approx(ls, abs=0.01)


def test_identical_markers_cannot_be_fitted() -> None:
    x = np.linspace(0, 1, 10)
    with pytest.raises(ValueError, match="not determined"):
        fit_sigma_least_squares(x, x, x + 1)
    with pytest.raises(ValueError, match="not determined"):
        fit_sigma_lms(x, x, x + 1)


def test_both_fits_hold_sigma_to_a_weighted_mean() -> None:
    """Errors of the same sign, the inner marker's three times the outer's: the unconstrained
    optimum is sigma = 1.5, which would extrapolate past the outer marker; the paper's fusion
    takes weights in [0, 1], and both fits give the constrained optimum, 1."""
    rng = np.random.default_rng(4)
    truth = rng.uniform(-20, 20, 500)
    error = rng.normal(0, 1.0, 500)
    outer, inner = truth + error, truth + 3.0 * error
    assert fit_sigma_least_squares(outer, inner, truth) == 1.0
    lms, _ = fit_sigma_lms(outer, inner, truth)
    assert lms == 1.0
    # and the other side: the outer marker the worse one by far
    assert fit_sigma_least_squares(inner, outer, truth) == 0.0


def _write_data(path: Path, outer_sd: float, inner_sd: float, shared: float = 0.0) -> None:
    """Markers with independent errors, the inner's also ``shared`` times the outer's (a
    common cause, such as the corners' bias on one frame, makes them correlate)."""
    rng = np.random.default_rng(4)
    n = 400
    truth = rng.uniform(-10, 10, (n, 4))
    truth[:, 2] = rng.uniform(30, 150, n)
    rows = [
        "true_x_cm,true_y_cm,true_z_cm,true_yaw_deg,"
        + ",".join(f"m{m}_{c}" for m in (0, 1) for c in ("x_cm", "y_cm", "z_cm", "yaw_deg"))
    ]
    outer = truth + rng.normal(0, outer_sd, truth.shape)
    inner = truth + shared * (outer - truth) + rng.normal(0, inner_sd, truth.shape)
    for t, a, b in zip(truth, outer, inner, strict=True):
        rows.append(",".join(f"{v:.6f}" for v in (*t, *a, *b)))
    path.write_text("\n".join(rows) + "\n")


def test_weights_at_their_bound_are_said_to_be_one_marker_alone(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """An inner marker whose error is three times the outer's and more (as on clean frames,
    where the big marker is far the better and both share the frame's corner bias) pins every
    weight at 1: fit-fusion says so for each, with both markers' errors, and points to the
    default fusion; independent, comparable markers give weights inside (0, 1) and no line."""
    from perchpose.cli import main

    lopsided, balanced = tmp_path / "lopsided.csv", tmp_path / "balanced.csv"
    _write_data(lopsided, 0.001, 0.002, shared=3.0)
    _write_data(balanced, 0.3, 0.5)
    assert main(["fit-fusion", str(lopsided)]) == 0
    err = capsys.readouterr().err
    assert err.count("sits at its bound (1.000)") == 4
    assert "the outer marker alone does best (rms error outer 0.0010 cm, inner 0.0034 cm)" in err
    assert "needs no fit" in err
    assert main(["fit-fusion", str(balanced)]) == 0
    assert "sits at its bound" not in capsys.readouterr().err

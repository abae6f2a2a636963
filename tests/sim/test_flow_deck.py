import json
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from perchpose.app.inputs import load_camera
from perchpose.app.perch import PerchCampaign, PerchOptions, run
from perchpose.errors import PerchposeError, SensingConfigError
from perchpose.geometry import rot_z
from perchpose.sim.disturbances import Disturbances, OdometryModel
from perchpose.sim.flow_deck import APERTURE_RAD, FLOW_HZ, WINDOW_PX, FlowDeck, FlowDeckError
from perchpose.sim.perch import PerchSetup, run_perch
from perchpose.sim.sensing import Sensing

STILL = np.zeros(3)


def noise_only(smoothing_s: float) -> FlowDeck:
    return FlowDeck(smoothing_s=(smoothing_s, smoothing_s), scale_error=0.0, gyro_mismatch=0.0)


def hover_errors(
    deck: FlowDeck, height_m: float, seconds: float, seed: int = 0, yaw_rate: float = 0.0
) -> np.ndarray:
    """The x error of each 10 ms sample hovering at ``height_m`` (body = world)."""
    error = FlowDeckError(deck, np.random.default_rng(seed))
    omega = np.array([0.0, 0.0, yaw_rate])
    n = int(seconds * FLOW_HZ)
    return np.array(
        [error.advance(1.0 / FLOW_HZ, height_m, STILL, np.eye(3), omega)[0] for _ in range(n)]
    )


def test_the_error_is_a_low_passed_pixel_noise_that_grows_with_height() -> None:
    """The stationary spread is the pixel noise's velocity at that height times
    sqrt(a / (2 - a)), a = dt / smoothing (a first-order low-pass of white noise), and it
    doubles from 1 m to 2 m."""
    deck = noise_only(0.15)
    alpha = (1.0 / FLOW_HZ) / 0.15
    for height in (1.0, 2.0):
        expected = (
            deck.pixel_noise_px
            * height
            * APERTURE_RAD
            / WINDOW_PX
            * FLOW_HZ
            * math.sqrt(alpha / (2 - alpha))
        )
        spread = float(np.std(hover_errors(deck, height, 300.0, seed=3)))
        assert spread == pytest.approx(expected, rel=0.08)
    assert expected == pytest.approx(0.06, abs=0.005)  # about 3 cm/s at 1 m, 6 at 2 m


def test_the_error_is_correlated_over_the_filters_time_constant() -> None:
    """White per sample it is not: one smoothing time later the error still correlates by
    about 1/e ((1 - dt / smoothing) per sample), and ten later not at all."""
    errors = hover_errors(noise_only(0.2), 1.0, 900.0, seed=5)

    def correlation(lag_s: float) -> float:
        k = int(round(lag_s * FLOW_HZ))
        return float(np.corrcoef(errors[:-k], errors[k:])[0, 1])

    assert correlation(0.2) == pytest.approx((1 - 0.01 / 0.2) ** 20, abs=0.05)
    assert abs(correlation(2.0)) < 0.06


def test_a_yaw_rate_adds_noise() -> None:
    deck = noise_only(0.1)
    still = float(np.std(hover_errors(deck, 1.0, 100.0, seed=1)))
    turning = float(np.std(hover_errors(deck, 1.0, 100.0, seed=1, yaw_rate=1.5)))
    assert turning > 1.1 * still


def test_rotation_left_after_the_gyro_and_a_scale_error_are_systematic() -> None:
    """Without pixel noise, a roll rate leaves the drawn share of h * omega, and a speed the
    drawn share of itself, once the filter has settled; both in the world frame."""
    deck = FlowDeck(pixel_noise_px=0.0, smoothing_s=(0.05, 0.05), rotation_blur=0.0)
    error = FlowDeckError(deck, np.random.default_rng(2))
    assert 0 < abs(error.scale) <= deck.scale_error
    R = rot_z(math.pi / 2)  # the body's x is the world's y
    for _ in range(200):
        e = error.advance(0.01, 1.5, np.array([0.0, 0.4, 0.0]), R, np.array([0.2, 0.0, 0.0]))
    body_x = error.scale * 0.4
    body_y = -error.gyro_share[1] * 1.5 * 0.2
    np.testing.assert_allclose(e, R @ np.array([body_x, body_y, 0.0]), atol=1e-9)


def test_the_odometry_drifts_further_on_a_flow_deck_than_on_white_noise() -> None:
    """Hovering 10 s at 1.5 m: the position's horizontal drift (the integral of the
    velocity's error) is several times what the same size of white noise gives."""

    def drift(flow: bool, seed: int) -> float:
        rng = np.random.default_rng(seed)
        deck = FlowDeckError(FlowDeck(), np.random.default_rng(seed + 1000)) if flow else None
        odometry = OdometryModel(Disturbances.none(), np.zeros(3), rng, 0.03, deck)
        p = np.array([0.0, 0.0, 1.5])
        for _ in range(500):  # 10 s at 50 Hz
            odometry.update(p, STILL, 0.02, np.eye(3), STILL)
        return float(np.hypot(*odometry.drift_m[:2]))

    white = np.median([drift(False, s) for s in range(30)])
    flow = np.median([drift(True, s) for s in range(30)])
    assert flow > 3 * white


def test_an_odometry_with_a_flow_deck_needs_the_attitude() -> None:
    deck = FlowDeckError(FlowDeck(), np.random.default_rng(0))
    odometry = OdometryModel(Disturbances.none(), np.zeros(3), np.random.default_rng(0), 0.0, deck)
    with pytest.raises(ValueError, match="attitude and body rates"):
        odometry.update(np.zeros(3), STILL, 0.02)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"pixel_noise_px": -1.0}, "pixel_noise_px must be a non-negative"),
        ({"smoothing_s": (0.0, 0.1)}, "smoothing_s must be 0 < low"),
        ({"smoothing_s": (0.3, 0.1)}, "smoothing_s must be 0 < low"),
        ({"min_height_m": math.nan}, "min_height_m must be positive"),
    ],
)
def test_a_bad_flow_deck_is_refused(kwargs: dict[str, object], message: str) -> None:
    with pytest.raises(SensingConfigError, match=message):
        FlowDeck(**kwargs)  # type: ignore[arg-type]


def test_an_unknown_odometry_is_refused(tmp_path: Path) -> None:
    with pytest.raises(SensingConfigError, match="unknown odometry 'bumpy'"):
        Sensing(odometry="bumpy")
    with pytest.raises(PerchposeError, match="--odometry: unknown 'bumpy'"):
        run(PerchOptions(str(tmp_path), estimators="truth", runs=1, odometry="bumpy"))


def test_a_campaign_on_a_flow_deck_says_so(tmp_path: Path) -> None:
    out = tmp_path / "flow"
    said: list[str] = []
    options = PerchOptions(str(out), estimators="truth", runs=1, workers=1, odometry="flow-deck")
    run(options, say=said.append)
    assert json.loads((out / "perch.json").read_text())["odometry"] == "flow-deck"
    sensing = json.loads((out / "campaign.json").read_text())["setup"]["sensing"]
    assert sensing["flow_deck"]["smoothing_s"] == [0.05, 0.25]
    assert any("flow-deck (correlated) odometry" in line for line in said)


def _magnet_wander_mm(setup: PerchSetup, seed: int) -> tuple[str, float]:
    """How the run ended, and the magnet's RMS distance from the target's axis over the
    frames within 10 cm under the plate."""
    result = run_perch(setup, seed)
    target = setup.T_world_target[:3, 3]
    aside = np.hypot(*(result.p_magnet_m[:, :2] - target[:2]).T)
    below = target[2] - result.p_magnet_m[:, 2]
    near = (below > 0.0) & (below < 0.1)
    return result.reason, float(np.sqrt(np.mean(aside[near] ** 2))) * 1000.0


@pytest.mark.parametrize("seed", [600020, 600021])
def test_the_inertial_filter_holds_the_magnet_on_a_flow_decks_odometry(seed: int) -> None:
    """Moderate wind, the true pose, velocity setpoints: on its own odometry the vehicle
    wanders 3 cm around the target's axis under the plate and never commits; with the
    inertial filter correcting the setpoints it holds within about a centimetre and perches."""
    campaign = PerchCampaign.from_options(
        load_camera("preset:fpv"),
        estimators="truth",
        runs=1,
        wind="moderate",
        odometry="flow-deck",
        command="velocity",
    )
    setup = campaign.setups[0]
    controller = setup.controller
    without = replace(
        setup, controller=replace(controller, inertial=replace(controller.inertial, enabled=False))
    )
    reason_with, wander_with = _magnet_wander_mm(setup, seed)
    reason_without, wander_without = _magnet_wander_mm(without, seed)
    assert reason_with == "perched"
    assert reason_without != "perched"
    assert wander_with < 0.5 * wander_without

"""What touches the plate first: the magnet's and the rotors' discs against a plate with edges."""

import itertools
import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from perchpose.errors import VehicleConfigError
from perchpose.sim.contact import (
    MAGNET,
    Contact,
    ContactRules,
    Magnet,
    PlateContact,
    PlateForces,
    PlateSurface,
    shared_area_m2,
    tilt_deg,
)
from perchpose.sim.quadrotor import Quadrotor, QuadrotorParams

PLATE_Z = 2.0


def vehicle_at(
    magnet_top_m: float, tilt: float = 0.0, about: str = "x", xy_m: tuple[float, float] = (0, 0)
) -> Quadrotor:
    """A vehicle whose magnet's top (``magnet_top_m`` above its centre) is 1 mm into the
    plate when level, tilted ``tilt`` degrees about body ``about``."""
    q = Quadrotor.hovering(QuadrotorParams(), np.array([*xy_m, PLATE_Z - magnet_top_m]), 0.0)
    q.R_world_body = Rotation.from_euler(about, tilt, degrees=True).as_matrix()
    q.p_m = np.array([*xy_m, PLATE_Z - magnet_top_m + 0.001])
    return q


def first(magnet_top_m: float, vehicle: Quadrotor) -> str | None:
    plate = PlateContact(PLATE_Z, (0.0, 0.0, magnet_top_m), ContactRules())
    return plate.contact.part if plate(vehicle) and plate.contact else None


def test_a_level_vehicle_touches_with_its_magnet() -> None:
    assert first(0.02, vehicle_at(0.02)) == MAGNET


def test_a_tilted_vehicle_strikes_with_a_rotor_unless_the_magnet_stands_clear() -> None:
    """The rotor plane 12 mm above the centre, hubs 32.5 mm out along x, 23.5 mm discs:
    pitched 15 deg, the rear rotors' rims stand 26 mm above the centre, the rim of a magnet
    whose top is 20 mm up only 22.6 mm: a rotor strikes first. A magnet 35 mm up stands
    clear (37 mm)."""
    low = vehicle_at(0.02, tilt=15.0, about="y")
    assert (first(0.02, low) or "").startswith("rotor")
    high = vehicle_at(0.035, tilt=15.0, about="y")
    assert first(0.035, high) == MAGNET


def test_nothing_beyond_the_plates_edge_touches() -> None:
    far = vehicle_at(0.035, xy_m=(0.3, 0.0))  # the plate's half size is 0.10 m
    assert first(0.035, far) is None
    edge = vehicle_at(0.035, xy_m=(0.09, 0.0))
    assert first(0.035, edge) == MAGNET


def test_the_rules_of_a_perch() -> None:
    rules = ContactRules()

    def verdict(**kw: object) -> str:
        base = {"part": MAGNET, "magnet_xy_m": (0.0, 0.0), "v_mps": (0.0, 0.0, 0.15)}
        return Contact(**{**base, "tilt_deg": 3.0, **kw}).verdict(rules)  # type: ignore[arg-type]

    assert verdict() == "perched"
    assert verdict(part="rotor 2") == "rotor-strike"
    assert verdict(magnet_xy_m=(0.010, 0.009)) == "off-centre"
    assert verdict(v_mps=(0.0, 0.0, 0.35)) == "too-fast"
    assert verdict(v_mps=(0.08, 0.08, 0.15)) == "sideways"
    assert verdict(tilt_deg=16.0) == "tilted"
    touch = Contact(MAGNET, (0.003, 0.004), (0.06, 0.08, 0.1), 2.0)
    assert touch.offset_mm == pytest.approx(5.0)
    assert touch.lateral_speed_mps == pytest.approx(0.1)
    assert touch.speed_mps == pytest.approx(math.sqrt(0.0036 + 0.0064 + 0.01))
    with pytest.raises(VehicleConfigError, match="must be positive"):
        ContactRules(max_tilt_deg=0.0)


def test_tilt_and_the_ceiling_effect_per_rotor() -> None:
    """Tilted under a ceiling, the rotors nearer it gain more thrust than those further."""
    q = vehicle_at(0.035, tilt=10.0, about="y")
    assert tilt_deg(q) == pytest.approx(10.0, abs=1e-9)
    q.ceiling_z_m = PLATE_Z
    gains = [q.ceiling_factor(i) for i in range(4)]
    # pitched nose down about y: the rear hubs (negative body x) rise towards the plate
    rear = [g for g, (hx, _) in zip(gains, q.hubs_m, strict=True) if hx < 0]
    front = [g for g, (hx, _) in zip(gains, q.hubs_m, strict=True) if hx > 0]
    assert min(rear) > max(front) > 1.0


def test_the_magnets_pull_against_distance_and_offset() -> None:
    """The formula's figures for the paper's 25 mm disc (3 mm of N35) on a soft-iron gear:
    the seated pull from B = Br L / sqrt(R^2 + L^2) (the image doubles the half-field),
    falling with the gap; a gear half off the magnet shares the lens two discs a radius
    apart make, R^2 (2 pi / 3 - sqrt(3) / 2)."""
    magnet = Magnet()
    R, L = 0.0125, 0.003
    seated = math.pi * R * R * (1.2 * L / math.hypot(R, L)) ** 2 / (2 * 4e-7 * math.pi)
    assert magnet.pull_n(0.0, 0.0) == pytest.approx(seated, rel=1e-12)
    assert magnet.pull_n(0.0, 0.0) == pytest.approx(15.3, abs=0.1)
    pulls = [magnet.pull_n(g, 0.0) for g in (0.0, 0.005, 0.01, 0.015, 0.03)]
    assert all(a > b for a, b in itertools.pairwise(pulls))
    weight_n = 0.039 * 9.81
    assert pulls[-1] < weight_n / 5 < weight_n < pulls[3]
    assert magnet.pull_n(0.06, 0.0) == 0.0  # beyond its reach
    lens = R * R * (2 * math.pi / 3 - math.sqrt(3) / 2)
    assert shared_area_m2(R, R, R) == pytest.approx(lens, rel=1e-12)
    assert shared_area_m2(R, R, 0.0) == pytest.approx(math.pi * R * R)
    assert shared_area_m2(R, R, 2.5 * R) == 0.0
    with pytest.raises(VehicleConfigError, match="magnet"):
        Magnet(remanence_t=0.0)


def _on_the_plate(
    xy_m: tuple[float, float] = (0.0, 0.0), tilt_deg: float = 0.0, below_m: float = -0.0002
) -> tuple[Quadrotor, PlateForces]:
    """A vehicle with its motors stopped, its gear (25 mm, 35 mm above its centre)
    ``below_m`` under the plate (negative: pressed in), tilted about body x."""
    q = Quadrotor.hovering(QuadrotorParams(), np.array([*xy_m, 1.0]), 0.0)
    q.R_world_body = Rotation.from_euler("x", tilt_deg, degrees=True).as_matrix()
    top = q.point_in_world((0.0, 0.0, 0.035))
    q.p_m = q.p_m + np.array([0.0, 0.0, PLATE_Z - below_m - top[2]])
    q.thrust_scale = (0.0,) * 4
    q.rotor_speed_rad_s = np.zeros(4)
    forces = PlateForces(PLATE_Z, (0.0, 0.0, 0.035), ContactRules(), Magnet(), PlateSurface())
    q.plate = forces
    return q, forces


def _hang(q: Quadrotor, seconds: float) -> None:
    for _ in range(int(seconds * 500)):
        q.step(1 / 500, np.zeros(4))


def test_a_seated_gear_holds_the_vehicle_with_its_motors_stopped() -> None:
    q, forces = _on_the_plate(xy_m=(0.006, 0.0))
    _hang(q, 1.0)
    assert forces.seated(q)
    assert abs(forces.gap_m(q)) < 0.001
    assert np.linalg.norm(q.v_mps) < 0.01
    assert np.linalg.norm(q.p_m[:2] - [0.006, 0.0]) < 0.002  # friction holds it in place


def test_a_gear_beside_the_magnet_does_not_hold() -> None:
    """26 mm off the magnet's centre the two 25 mm discs share nothing: the vehicle falls."""
    q, forces = _on_the_plate(xy_m=(0.026, 0.0))
    _hang(q, 0.3)
    assert forces.gap_m(q) > 0.1


def test_only_a_gear_under_the_plate_is_at_it() -> None:
    """A gear 3 mm under the plate is at it; the same height beside the plate's edge (the
    plate is 20 cm square) is free air, whatever its gap to the plate's plane says."""
    q, forces = _on_the_plate(below_m=0.003)
    assert forces.at_plate(q, 0.005)
    assert not forces.at_plate(q, 0.002)
    beside, forces = _on_the_plate(below_m=-0.04, xy_m=(0.0, 1.6))
    assert forces.gap_m(beside) < 0.0
    assert not forces.at_plate(beside, 0.005)


def test_the_magnet_seats_a_gear_that_touched_with_its_rim() -> None:
    """Touching 8 degrees tilted, 1 mm into the plate at its rim: the pull at the gear's
    centre against the rim's reaction turns the vehicle flat (a pendulum hanging from it)."""
    q, forces = _on_the_plate(tilt_deg=8.0, below_m=0.0)
    assert not forces.seated(q)
    _hang(q, 1.0)
    assert forces.seated(q)
    assert tilt_deg(q) < 1.0


def test_the_magnet_pulls_the_vehicle_up_from_a_centimetre() -> None:
    """Hovering 10 mm under the plate, the magnet's 2.6 N against 0.38 N of weight snaps it
    on; the plate stops it, and it does not bounce off."""
    q, forces = _on_the_plate(below_m=0.010)
    _hang(q, 0.5)
    assert forces.seated(q)


def test_a_plate_contact_that_goes_on_reports_a_rotor_strike_after_the_magnet() -> None:
    rules = ContactRules()
    plate = PlateContact(PLATE_Z, (0.0, 0.0, 0.035), rules, goes_on=True)
    assert not plate(vehicle_at(0.035))  # the magnet: the flight goes on
    assert plate.contact is not None
    assert plate.contact.part == MAGNET
    assert plate.struck is None
    assert plate(vehicle_at(0.035, tilt=25.0, about="y"))  # then a rotor: it ends
    assert plate.struck is not None
    assert plate.struck.startswith("rotor")
    assert plate.contact.part == MAGNET  # the first contact stays the first


def test_a_hanging_vehicle_in_wind_sticks_where_it_seated() -> None:
    """Seated 15 mm off the magnet's centre (a third of its pull) with its motors stopped,
    in 5 m/s of wind for 3 s: friction holds the gear where it touched (it does not creep
    off the magnet's edge)."""
    q, forces = _on_the_plate(xy_m=(0.015, 0.0))
    q.wind_mps = (0.0, 5.0, 0.0)
    _hang(q, 3.0)
    assert forces.seated(q)
    assert np.linalg.norm(q.point_in_world((0.0, 0.0, 0.035))[:2] - np.array([0.015, 0.0])) < 5e-4

"""What touches the plate first: the magnet's and the rotors' discs against a plate with edges."""

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from perchpose.errors import VehicleConfigError
from perchpose.sim.contact import MAGNET, Contact, ContactRules, PlateContact, tilt_deg
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

"""What touches the plate first, and whether the vehicle survives the contact.

The vehicle is not a point: a magnet (a disc of ``magnet_radius_m``, its top face at the
controller's ``p_body_magnet_m``) sits on top of a body whose four rotor discs
(``QuadrotorParams.prop_radius_m``, hubs at ``arm_m`` along body x and y) turn in a plane
``rotor_plane_m`` above the centre of mass. Tilted, a disc's highest point is on its rim, at
``r * sin(tilt)`` above its centre; a rotor can reach the plate before the magnet does. The
plate is a square of ``plate_half_size_m`` around the target's centre: a part beyond its edge
touches nothing.

A perch is scored at the first contact, against ``ContactRules``: the magnet touched first,
within ``max_offset_mm`` of the target's centre (the paper's 25 mm magnet over the target's
centre), the full speed under ``max_speed_mps``, the lateral speed under
``max_lateral_speed_mps`` and the tilt under ``max_tilt_deg`` (a vehicle holding station in
4.5 m/s of wind already leans about 9 deg).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from perchpose.errors import VehicleConfigError, require_positive
from perchpose.sim.quadrotor import Quadrotor

MAGNET = "magnet"
ROTORS = ("rotor 1", "rotor 2", "rotor 3", "rotor 4")
NEAR_M = 0.06  # parts are looked at only once the magnet is this close below the plate


@dataclass(frozen=True)
class ContactRules:
    """The magnet, the plate and what a contact must be to count as a perch (SI units)."""

    magnet_radius_m: float = 0.0125
    plate_half_size_m: float = 0.10
    max_offset_mm: float = 12.5
    max_speed_mps: float = 0.3
    max_lateral_speed_mps: float = 0.1
    max_tilt_deg: float = 15.0

    def __post_init__(self) -> None:
        names = (
            "magnet_radius_m",
            "plate_half_size_m",
            "max_offset_mm",
            "max_speed_mps",
            "max_lateral_speed_mps",
            "max_tilt_deg",
        )
        require_positive(self, names, VehicleConfigError, "contact rule ")


@dataclass(frozen=True)
class Contact:
    """The first contact: which part, where the magnet's centre was (world, m), the
    vehicle's velocity (world, m/s) and its tilt."""

    part: str
    magnet_xy_m: tuple[float, float]
    v_mps: tuple[float, float, float]
    tilt_deg: float

    @property
    def offset_mm(self) -> float:
        return 1000.0 * math.hypot(*self.magnet_xy_m)

    @property
    def lateral_speed_mps(self) -> float:
        return math.hypot(self.v_mps[0], self.v_mps[1])

    @property
    def speed_mps(self) -> float:
        return math.sqrt(sum(v * v for v in self.v_mps))

    def verdict(self, rules: ContactRules) -> str:
        """``perched``, or the first rule the contact broke."""
        if self.part != MAGNET:
            return "rotor-strike"
        if self.offset_mm > rules.max_offset_mm:
            return "off-centre"
        if self.speed_mps >= rules.max_speed_mps:
            return "too-fast"
        if self.lateral_speed_mps >= rules.max_lateral_speed_mps:
            return "sideways"
        if self.tilt_deg >= rules.max_tilt_deg:
            return "tilted"
        return "perched"


def tilt_deg(vehicle: Quadrotor) -> float:
    """The angle between the body's z axis and the world's vertical."""
    return math.degrees(math.acos(max(-1.0, min(1.0, float(vehicle.R_world_body[2, 2])))))


class PlateContact:
    """Watches a vehicle against the plate at ``plate_z_m`` (centred on x = y = 0): call it
    after each physics step; True once a part touches (``contact`` says which)."""

    def __init__(
        self, plate_z_m: float, magnet_top_body_m: tuple[float, float, float], rules: ContactRules
    ) -> None:
        self.plate_z_m = plate_z_m
        self.magnet_top = magnet_top_body_m
        self.rules = rules
        self.contact: Contact | None = None

    @staticmethod
    def _disc_top(
        vehicle: Quadrotor,
        centre_body: tuple[float, float, float],
        radius_m: float,
        normal: tuple[float, float, float],
    ) -> tuple[float, float, float]:
        """The highest point of a disc fixed to the body, parallel to its rotor plane (whose
        ``normal`` is the body's z axis in the world)."""
        cx, cy, cz = vehicle.point_in_world(centre_body)
        nx, ny, nz = normal
        across = math.sqrt(max(0.0, 1.0 - nz * nz))  # |e_z - n n_z|
        if across < 1e-9:
            return cx, cy, cz
        k = radius_m / across
        return cx - k * nx * nz, cy - k * ny * nz, cz + radius_m * across

    def _on_plate(self, x: float, y: float, z: float) -> bool:
        h = self.rules.plate_half_size_m
        return z >= self.plate_z_m and abs(x) <= h and abs(y) <= h

    def __call__(self, vehicle: Quadrotor) -> bool:
        if vehicle.point_in_world(self.magnet_top)[2] < self.plate_z_m - NEAR_M:
            return False
        params = vehicle.params
        R = vehicle.R_world_body
        up = (float(R[0, 2]), float(R[1, 2]), float(R[2, 2]))
        parts = [(MAGNET, self._disc_top(vehicle, self.magnet_top, self.rules.magnet_radius_m, up))]
        for name, (hx, hy) in zip(ROTORS, vehicle.hubs_m, strict=True):
            hub = (hx, hy, params.rotor_plane_m)
            parts.append((name, self._disc_top(vehicle, hub, params.prop_radius_m, up)))
        touching = [(top[2], name) for name, top in parts if self._on_plate(*top)]
        if not touching:
            return False
        _, part = max(touching)  # the one furthest into the plate got there first
        magnet = vehicle.point_in_world(self.magnet_top)
        v = vehicle.v_mps
        self.contact = Contact(
            part,
            (magnet[0], magnet[1]),
            (float(v[0]), float(v[1]), float(v[2])),
            tilt_deg(vehicle),
        )
        return True

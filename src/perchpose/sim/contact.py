"""What touches the plate first, and whether the vehicle survives the contact.

The vehicle is not a point: a magnet (a disc of ``magnet_radius_m``, its top face at the
controller's ``p_body_magnet_m``) sits on top of a body whose four rotor discs
(``QuadrotorParams.prop_radius_m``, hubs at ``arm_m`` along body x and y) turn in a plane
``rotor_plane_m`` above the centre of mass. Tilted, a disc's highest point is on its rim, at
``r * sin(tilt)`` above its centre; a rotor can reach the plate before the magnet does. The
plate is a square of ``plate_half_size_m`` around the target's centre: a part beyond its edge
touches nothing.

``PlateContact`` says what touched first. With ``--contact first-touch`` a perch is scored
there, against ``ContactRules``: the magnet touched first, within ``max_offset_mm`` of the
target's centre (the paper's 25 mm magnet over the target's centre), the full speed under
``max_speed_mps``, the lateral speed under ``max_lateral_speed_mps`` and the tilt under
``max_tilt_deg`` (a vehicle holding station in 4.5 m/s of wind already leans about 9 deg).

With ``--contact hold`` (the default) the flight goes on through the contact: ``PlateForces``
gives the vehicle the plate's reaction and friction at its gear's rim and the magnet's pull
(``Magnet``), and a perch is a gear seated on the plate and held by the magnet after the motors
stopped (``perchpose.sim.perch``).

The magnet: the plate's magnet is the paper's 25 mm disc, taken as an axially magnetised N35
cylinder 3 mm thick (remanence 1.2 T); the vehicle's gear is a soft-iron disc of the same
diameter on top of the vehicle. On the magnet's axis, at a distance ``g`` from its face, the
field of a uniformly magnetised cylinder (radius ``R``, length ``L``) is
``Br / 2 * ((g + L) / sqrt(R^2 + (g + L)^2) - g / sqrt(R^2 + g^2))``; a soft-iron face doubles
it at its surface (the magnet's image), and Maxwell's pull on a face of area ``A`` in a field
``B`` is ``A B^2 / (2 mu0)``. ``A`` is the area the gear's face shares with the magnet's (two
discs ``offset`` apart). That gives 15.3 N seated, 7.9 N at 5 mm, 2.6 N at 10 mm, 0.8 N at
15 mm, 0.26 N at 20 mm and 0.04 N at 30 mm (the 39 g vehicle weighs 0.38 N). For magnets seated on
thick steel the same formula gives 1.4 to 2.2 times less than finite-element results and
catalogue figures (QuickField's published examples: 381 N against 510-542 N for a 50.8 x
16.5 mm N35 disc; 1.15 N against 2.56 N for a 4.8 x 0.8 mm N40 disc); a thin gear takes less
than a thick plate, so the figures here are on the weak side. The magnet's pull across the
plate (towards its centre) is left out, which is also on the weak side.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from perchpose.errors import VehicleConfigError, require_positive
from perchpose.sim.quadrotor import Mat3, Quadrotor, Vec3, mat3, vec3

MU0 = 4e-7 * math.pi  # the vacuum's permeability, T m / A
RIM_POINTS = 8  # points on the gear's rim that take the plate's reaction
SUBSTEPS = (
    20  # integration steps per physics step while the gear is at the plate (0.1 ms at 500 Hz)
)

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


@dataclass(frozen=True)
class Magnet:
    """The plate's magnet (a disc, axially magnetised) and the vehicle's soft-iron gear (a disc
    of ``gear_radius_m``), SI units; ``reach_m``: beyond this gap the pull is taken as none."""

    radius_m: float = 0.0125
    thickness_m: float = 0.003
    remanence_t: float = 1.2
    gear_radius_m: float = 0.0125
    reach_m: float = 0.05

    def __post_init__(self) -> None:
        names = ("radius_m", "thickness_m", "remanence_t", "gear_radius_m", "reach_m")
        require_positive(self, names, VehicleConfigError, "magnet ")

    def field_t(self, gap_m: float) -> float:
        """The field at the gear's face ``gap_m`` from the magnet's, on its axis (T)."""
        R, L, g = self.radius_m, self.thickness_m, max(0.0, gap_m)
        return self.remanence_t * (
            (g + L) / math.sqrt(R * R + (g + L) ** 2) - g / math.sqrt(R * R + g * g)
        )

    def pull_n(self, gap_m: float, offset_m: float) -> float:
        """The magnet's pull on the gear (N), its faces ``gap_m`` apart and its centre
        ``offset_m`` off the magnet's axis."""
        if gap_m > self.reach_m:
            return 0.0
        area = shared_area_m2(self.radius_m, self.gear_radius_m, offset_m)
        return area * self.field_t(gap_m) ** 2 / (2.0 * MU0)


def shared_area_m2(r1_m: float, r2_m: float, apart_m: float) -> float:
    """The area two discs of radii ``r1_m`` and ``r2_m`` share, their centres ``apart_m``
    apart."""
    d = abs(apart_m)
    if d >= r1_m + r2_m:
        return 0.0
    small, large = min(r1_m, r2_m), max(r1_m, r2_m)
    if d <= large - small:
        return math.pi * small * small
    a1 = math.acos((d * d + r1_m * r1_m - r2_m * r2_m) / (2.0 * d * r1_m))
    a2 = math.acos((d * d + r2_m * r2_m - r1_m * r1_m) / (2.0 * d * r2_m))
    kite = 0.5 * math.sqrt(
        max(0.0, (-d + r1_m + r2_m) * (d + r1_m - r2_m) * (d - r1_m + r2_m) * (d + r1_m + r2_m))
    )
    return r1_m * r1_m * a1 + r2_m * r2_m * a2 - kite


@dataclass(frozen=True)
class PlateSurface:
    """How the plate takes the gear: a stiff face (``stiffness_n_per_m`` over the whole gear,
    with ``damping_n_s_per_m``; about 0.3 mm under the magnet's seated pull) and Coulomb
    friction ``friction`` (steel on a printed plate) at the gear's centre: the gear sticks
    where it touched, held there by a stiff tangential spring (``stick_n_per_m``, with
    ``stick_damping_n_s_per_m``: a twentieth of a millimetre under 0.1 N), until the force
    needed passes the friction's limit, when it slides with the limit against it."""

    stiffness_n_per_m: float = 5.0e4
    damping_n_s_per_m: float = 80.0
    friction: float = 0.4
    stick_n_per_m: float = 2000.0
    stick_damping_n_s_per_m: float = 8.0

    def __post_init__(self) -> None:
        names = (
            "stiffness_n_per_m",
            "damping_n_s_per_m",
            "friction",
            "stick_n_per_m",
            "stick_damping_n_s_per_m",
        )
        require_positive(self, names, VehicleConfigError, "plate ")


class PlateForces:
    """The plate's forces on a vehicle near it (``Quadrotor.plate``): the magnet's pull at
    the gear's centre, at each of ``RIM_POINTS`` points on the gear's rim that is pressed into
    the plate's face (within its square) the face's reaction, and the friction of them all
    at the gear's centre (``PlateSurface``; where the gear sticks is this object's state).
    World forces and body torques about the centre of mass."""

    def __init__(
        self,
        plate_z_m: float,
        gear_top_body_m: tuple[float, float, float],
        rules: ContactRules,
        magnet: Magnet,
        surface: PlateSurface,
    ) -> None:
        self.plate_z_m = plate_z_m
        self.centre = gear_top_body_m
        self.half_m = rules.plate_half_size_m
        self.radius_m = rules.magnet_radius_m
        self.magnet = magnet
        self.surface = surface
        cx, cy, cz = gear_top_body_m
        r = self.radius_m
        self.rim = tuple(
            (cx + r * math.cos(a), cy + r * math.sin(a), cz)
            for a in (2.0 * math.pi * i / RIM_POINTS for i in range(RIM_POINTS))
        )
        self.k_n_per_m = surface.stiffness_n_per_m / RIM_POINTS
        self.c_n_s_per_m = surface.damping_n_s_per_m / RIM_POINTS
        self.stuck_at: tuple[float, float] | None = None  # where the gear sticks (world x, y)

    def _gap_m(self, p: Vec3, R: Mat3) -> float:
        cx, cy, cz = self.centre
        return self.plate_z_m - (p[2] + R[2][0] * cx + R[2][1] * cy + R[2][2] * cz)

    def substeps(self, p: Vec3, R: Mat3) -> int:
        """How many integration steps a physics step takes: more while the gear's rim can
        reach the plate (its stiffness needs them)."""
        return SUBSTEPS if self._gap_m(p, R) < self.radius_m + 0.002 else 1

    def wrench(self, p: Vec3, v: Vec3, R: Mat3, w: Vec3) -> tuple[Vec3, Vec3] | None:
        """(world force N, body torque N m) on the vehicle, or None when the plate is out of
        reach."""
        gap = self._gap_m(p, R)
        if gap > self.magnet.reach_m:
            return None
        cx, cy, cz = self.centre
        x = p[0] + R[0][0] * cx + R[0][1] * cy + R[0][2] * cz
        y = p[1] + R[1][0] * cx + R[1][1] * cy + R[1][2] * cz
        pull = self.magnet.pull_n(gap, math.hypot(x, y)) if R[2][2] > 0.0 else 0.0
        Fx, Fy, Fz = 0.0, 0.0, pull
        # the pull is along world z; in the body (R^T e_z) times the lever
        bx, by, bz = pull * R[2][0], pull * R[2][1], pull * R[2][2]
        Tx, Ty, Tz = cy * bz - cz * by, cz * bx - cx * bz, cx * by - cy * bx
        normal = self._pressed(p, v, R, w) if gap < self.radius_m + 0.001 else None
        if normal is None:
            self.stuck_at = None
            return (Fx, Fy, Fz), (Tx, Ty, Tz)
        total, (nx, ny, nz) = normal
        fx, fy = self._friction(total, (x, y), p, v, R, w)
        Fx, Fy, Fz = Fx + fx, Fy + fy, Fz - total
        # the face's reactions (their torque about the centre) and the friction at the centre
        bx = R[0][0] * fx + R[1][0] * fy
        by = R[0][1] * fx + R[1][1] * fy
        bz = R[0][2] * fx + R[1][2] * fy
        Tx += nx + cy * bz - cz * by
        Ty += ny + cz * bx - cx * bz
        Tz += nz + cx * by - cy * bx
        return (Fx, Fy, Fz), (Tx, Ty, Tz)

    def _pressed(self, p: Vec3, v: Vec3, R: Mat3, w: Vec3) -> tuple[float, Vec3] | None:
        """The face's reaction on the gear's rim points pressed into it: the total (N, down
        on the vehicle) and its torque about the centre of mass (body frame); None where no
        point presses."""
        total = 0.0
        Tx = Ty = Tz = 0.0
        wx, wy, wz = w
        for qx, qy, qz in self.rim:
            pen = p[2] + R[2][0] * qx + R[2][1] * qy + R[2][2] * qz - self.plate_z_m
            if pen <= 0.0:
                continue
            px = p[0] + R[0][0] * qx + R[0][1] * qy + R[0][2] * qz
            py = p[1] + R[1][0] * qx + R[1][1] * qy + R[1][2] * qz
            if abs(px) > self.half_m or abs(py) > self.half_m:
                continue
            # the point's vertical speed: v + R (w x q), its z
            ux, uy, uz = wy * qz - wz * qy, wz * qx - wx * qz, wx * qy - wy * qx
            vz = v[2] + R[2][0] * ux + R[2][1] * uy + R[2][2] * uz
            normal = self.k_n_per_m * pen + self.c_n_s_per_m * vz
            if normal <= 0.0:
                continue
            total += normal
            bx, by, bz = -normal * R[2][0], -normal * R[2][1], -normal * R[2][2]
            Tx += qy * bz - qz * by
            Ty += qz * bx - qx * bz
            Tz += qx * by - qy * bx
        return (total, (Tx, Ty, Tz)) if total > 0.0 else None

    def _friction(
        self,
        normal_n: float,
        centre_xy: tuple[float, float],
        p: Vec3,
        v: Vec3,
        R: Mat3,
        w: Vec3,
    ) -> tuple[float, float]:
        """The friction on the gear's centre (world x, y, N) under ``normal_n`` of the face's
        reaction: the sticking spring's pull back to where it stuck, or the sliding limit
        (which moves the sticking point along)."""
        s = self.surface
        x, y = centre_xy
        if self.stuck_at is None:
            self.stuck_at = (x, y)
        cx, cy, cz = self.centre
        wx, wy, wz = w
        ux, uy, uz = wy * cz - wz * cy, wz * cx - wx * cz, wx * cy - wy * cx
        vx = v[0] + R[0][0] * ux + R[0][1] * uy + R[0][2] * uz
        vy = v[1] + R[1][0] * ux + R[1][1] * uy + R[1][2] * uz
        ax, ay = self.stuck_at
        k, c = s.stick_n_per_m, s.stick_damping_n_s_per_m
        fx = -k * (x - ax) - c * vx
        fy = -k * (y - ay) - c * vy
        limit = s.friction * normal_n
        size = math.hypot(fx, fy)
        if size > limit:  # sliding: the limit, and the sticking point follows the gear
            fx, fy = fx * limit / size, fy * limit / size
            self.stuck_at = (x + (fx + c * vx) / k, y + (fy + c * vy) / k)
        return fx, fy

    def seated(self, vehicle: Quadrotor, within_m: float = 0.001) -> bool:
        """The gear's whole face is within ``within_m`` of the plate, under it."""
        R = vehicle.R_world_body
        p = vehicle.p_m
        for qx, qy, qz in self.rim:
            z = float(p[2] + R[2, 0] * qx + R[2, 1] * qy + R[2, 2] * qz)
            x = float(p[0] + R[0, 0] * qx + R[0, 1] * qy + R[0, 2] * qz)
            y = float(p[1] + R[1, 0] * qx + R[1, 1] * qy + R[1, 2] * qz)
            if z < self.plate_z_m - within_m or max(abs(x), abs(y)) > self.half_m:
                return False
        return True

    def gap_m(self, vehicle: Quadrotor) -> float:
        """How far the gear's centre is below the plate (negative: pressed into it)."""
        return self._gap_m(vec3(vehicle.p_m), mat3(vehicle.R_world_body))

    def at_plate(self, vehicle: Quadrotor, within_m: float) -> bool:
        """The gear's centre is under the plate (within its square) and less than
        ``within_m`` below it; beside the plate there is nothing to stop against."""
        x, y, _ = vehicle.point_in_world(self.centre)
        return max(abs(x), abs(y)) <= self.half_m and self.gap_m(vehicle) < within_m


def tilt_deg(vehicle: Quadrotor) -> float:
    """The angle between the body's z axis and the world's vertical."""
    return math.degrees(math.acos(max(-1.0, min(1.0, float(vehicle.R_world_body[2, 2])))))


class PlateContact:
    """Watches a vehicle against the plate at ``plate_z_m`` (centred on x = y = 0): call it
    after each physics step. ``contact`` is the first contact (which part, where, how fast).
    The call is True at that first contact; where the flight goes on through the contact
    (``goes_on``), it is True instead when a rotor touches the plate (``struck`` names it),
    at the first contact or after it."""

    def __init__(
        self,
        plate_z_m: float,
        magnet_top_body_m: tuple[float, float, float],
        rules: ContactRules,
        goes_on: bool = False,
    ) -> None:
        self.plate_z_m = plate_z_m
        self.magnet_top = magnet_top_body_m
        self.rules = rules
        self.goes_on = goes_on
        self.contact: Contact | None = None
        self.struck: str | None = None

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
        touching = sorted(((top[2], name) for name, top in parts if self._on_plate(*top)))
        if not touching:
            return False
        first = self.contact is None
        if first:
            part = touching[-1][1]  # the one furthest into the plate got there first
            magnet = vehicle.point_in_world(self.magnet_top)
            v = vehicle.v_mps
            self.contact = Contact(
                part,
                (magnet[0], magnet[1]),
                (float(v[0]), float(v[1]), float(v[2])),
                tilt_deg(vehicle),
            )
            if not self.goes_on:
                return True
        rotors = [name for _, name in reversed(touching) if name != MAGNET]
        if self.goes_on and rotors:
            self.struck = rotors[0]
            return True
        return False

"""The model's onboard loops against the Crazyflie firmware's, side by side: a velocity step,
a gust, a lean, and the height through a take-over and a steep lean.

    .venv/bin/python benchmarks/bench_agreement.py [--out docs/agreement.png]

Three vehicles hover 1.9 m up (where the plate is): this package's model of the flight
controller (``sim.quadrotor``, stock velocity gain 4.3 /s), the firmware's PID
(``sim.firmware``, ``crazyflie-pid``, its stock gains), both flying the true velocity and
attitude, and the firmware's PID flying its own Kalman filter on a simulated IMU, Flow deck
and range sensor (``sim.onboard_kalman``). Each is asked for 0.3 m/s along x (cflib's world
velocity setpoint) for 2 s; then, hovering afresh, a 3 m/s wind along x starts at once and
blows for 3 s (the moderate level's mean, with no turbulence); then, hovering afresh, a 5 deg
nose-down pitch is asked for 1 s (cflib's ``send_zdistance_setpoint``, the height held where
the vehicle is); then, hovering afresh, the height is held where the vehicle is for 3 s (a
change of setpoint mode: the firmware's PID reinitialises its integrals), a 20 deg pitch
is asked for 1.5 s and a level one for 2 s. The figure shows the velocity in the step, the
drift in the gust, the pitch in the lean and the height in the last; the lines say the
step's time to 63 % and its overshoot, the gust's largest drift and where it settles, the
lean's time to 63 % and its largest pitch, the take-over's sink and the steep lean's lowest
and highest height.
Needs ``cffirmware`` (``../shared/firmware/install-cffirmware``).
"""

from __future__ import annotations

import argparse
from collections.abc import Callable

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from perchpose.geometry import roll_pitch_rad
from perchpose.sim.firmware import FirmwareQuadrotor, load_firmware
from perchpose.sim.flow_deck import FlowDeck
from perchpose.sim.onboard_kalman import CrazyflieKalman, KalmanSenses
from perchpose.sim.quadrotor import AttitudeHold, Quadrotor, QuadrotorParams

DT = 1 / 500
START = np.array([0.0, 0.0, 1.9])
STEP_MPS = 0.3
STEP_S = 2.0
WIND_MPS = 3.0
GUST_S = 3.0
LEAN_DEG = 5.0
LEAN_S = 1.0
# the take-over (level, s), then a steep lean (deg, s) and level again (s)
HEIGHT_PLAN = ((3.0, 0.0), (1.5, 20.0), (2.0, 0.0))


def model() -> Quadrotor:
    return Quadrotor.hovering(QuadrotorParams(), START, 0.0)


def firmware() -> Quadrotor:
    q = FirmwareQuadrotor.hovering_on_firmware(
        "crazyflie-pid", 500.0, QuadrotorParams(), START, 0.0
    )
    q.settle()
    return q


def firmware_on_kalman() -> Quadrotor:
    q = firmware()
    kalman = CrazyflieKalman(
        load_firmware(), KalmanSenses(), FlowDeck(), np.random.default_rng(1), q
    )
    kalman.settle(q)
    q.estimator = kalman
    return q


VEHICLES: dict[str, Callable[[], Quadrotor]] = {
    "model": model,
    "firmware PID": firmware,
    "firmware PID on its Kalman filter": firmware_on_kalman,
}


def fly(q: Quadrotor, seconds: float, v_sp: tuple[float, float, float]) -> np.ndarray:
    """(t, x, vx) at each step."""
    rows = []
    for i in range(round(seconds / DT)):
        q.fly(DT, 1, np.array(v_sp), 0.0, q.v_mps)
        rows.append((i * DT, float(q.p_m[0]), float(q.v_mps[0])))
    return np.array(rows)


def lean(q: Quadrotor) -> np.ndarray:
    """(t, pitch in deg) at each step of a lean asked from a hover, the height held where the
    vehicle's estimate puts it."""
    rows = []
    for i in range(round(LEAN_S / DT)):
        p_est = q.estimator.position if q.estimator is not None else q.p_m
        p = (float(p_est[0]), float(p_est[1]), float(p_est[2]))
        q.hold = AttitudeHold(0.0, np.radians(LEAN_DEG), 0.0, p[2], p)
        q.fly(DT, 1, np.zeros(3), 0.0, q.v_mps)
        rows.append((i * DT, np.degrees(roll_pitch_rad(q.R_world_body)[1])))
    return np.array(rows)


def height(q: Quadrotor) -> np.ndarray:
    """(t, height in mm from the start) at each step of ``HEIGHT_PLAN``'s attitude setpoints,
    the height held where the vehicle began, on its own estimate."""
    rows = []
    z0_m = float(q.p_m[2])
    t_s = 0.0
    for seconds, pitch_deg in HEIGHT_PLAN:
        for _ in range(round(seconds / DT)):
            p_est = q.estimator.position if q.estimator is not None else q.p_m
            p = (float(p_est[0]), float(p_est[1]), float(p_est[2]))
            q.hold = AttitudeHold(0.0, np.radians(pitch_deg), 0.0, z0_m, p)
            q.fly(DT, 1, np.zeros(3), 0.0, q.v_mps)
            t_s += DT
            rows.append((t_s, 1000.0 * (float(q.p_m[2]) - z0_m)))
    return np.array(rows)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="docs/agreement.png")
    args = parser.parse_args()
    fig, (ax_step, ax_gust, ax_lean, ax_height) = plt.subplots(1, 4, figsize=(18, 3.8))
    for name, make in VEHICLES.items():
        step = fly(make(), STEP_S, (STEP_MPS, 0.0, 0.0))
        t, vx = step[:, 0], step[:, 2]
        rise_s = float(t[np.argmax(vx >= 0.63 * STEP_MPS)])
        overshoot = max(0.0, float(vx.max()) / STEP_MPS - 1.0)
        q = make()
        q.wind_mps = (WIND_MPS, 0.0, 0.0)
        gust = fly(q, GUST_S, (0.0, 0.0, 0.0))
        drift_mm = 1000.0 * (gust[:, 1] - START[0])
        leant = lean(make())
        lean_s = float(leant[np.argmax(leant[:, 1] >= 0.63 * LEAN_DEG), 0])
        heights = height(make())
        take_over = heights[heights[:, 0] <= HEIGHT_PLAN[0][0], 1]
        steep = heights[heights[:, 0] > HEIGHT_PLAN[0][0], 1] - take_over[-1]
        print(
            f"{name}: step 63 % in {rise_s:.3f} s, overshoot {100 * overshoot:.0f} %; "
            f"gust drift max {np.abs(drift_mm).max():.0f} mm, after {GUST_S:g} s "
            f"{drift_mm[-1]:.0f} mm; lean 63 % in {lean_s:.3f} s, "
            f"largest {leant[:, 1].max():.2f} deg; take-over sink {take_over.min():.0f} mm, "
            f"steep lean {steep.min():.0f} / +{steep.max():.0f} mm"
        )
        ax_step.plot(t, vx, label=name)
        ax_gust.plot(gust[:, 0], drift_mm, label=name)
        ax_lean.plot(leant[:, 0], leant[:, 1], label=name)
        ax_height.plot(heights[:, 0], heights[:, 1], label=name)
    ax_step.axhline(STEP_MPS, color="grey", lw=0.8, ls="--")
    ax_step.set(xlabel="time (s)", ylabel="velocity x (m/s)", title=f"{STEP_MPS} m/s asked along x")
    ax_gust.set(
        xlabel="time (s)",
        ylabel="drift x (mm)",
        title=f"a {WIND_MPS:g} m/s wind starts, hover asked",
    )
    ax_lean.axhline(LEAN_DEG, color="grey", lw=0.8, ls="--")
    ax_lean.set(xlabel="time (s)", ylabel="pitch (deg)", title=f"a {LEAN_DEG:g} deg lean asked")
    lean_at_s = HEIGHT_PLAN[0][0]
    ax_height.axvspan(lean_at_s, lean_at_s + HEIGHT_PLAN[1][0], color="grey", alpha=0.15)
    ax_height.set(
        xlabel="time (s)",
        ylabel="height (mm)",
        title=f"take-over, then a {HEIGHT_PLAN[1][1]:g} deg lean (shaded)",
    )
    ax_step.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(args.out, dpi=110)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()

"""The Crazyflie firmware's own controllers flying the simulated vehicle.

``perchpose perch --flight-controller crazyflie-pid`` (or ``-mellinger``, ``-brescianini``,
``-lee``) puts the firmware's controller, compiled from its C sources as the Python module
``cffirmware`` (``../shared/firmware/``: Bitcraze's ``make bindings_python``; GPL-3.0, an
optional extra the user builds, imported only here and only when asked for), in place of the
model's onboard loops (``sim.quadrotor``). The plant stays ``Quadrotor``.

At each physics step the firmware runs its main loop's ticks (1 kHz; its controllers run their
attitude loop every second tick, 500 Hz, and the position loop every tenth, 100 Hz, as
``RATE_DO_EXECUTE`` decides), given:

- the setpoint as the Crazyflie's commander decodes cflib's ``send_velocity_world_setpoint``
  (``TYPE_VELOCITY_WORLD``: world velocity in m/s on x, y and z, the yaw rate in deg/s,
  counter-clockwise positive, in velocity mode on every axis), or, while the vehicle holds a
  full-state setpoint (``Quadrotor.hold``), ``send_full_state_setpoint`` (``TYPE_FULL_STATE``:
  absolute position, the yaw from the orientation's quaternion), or, while it holds an attitude
  setpoint, ``send_zdistance_setpoint`` (``TYPE_ZDISTANCE``: roll and pitch absolute in
  degrees, the height absolute, the yaw rate; x and y disabled, so the PID flies the lean
  asked and only its height loop is its own);
- the state estimate: the attitude as the firmware keeps it (roll, pitch and yaw in degrees,
  the pitch's sign flipped as the firmware's legacy convention has it, and the quaternion),
  the velocity the odometry gives (world frame), the position (the vehicle's own estimate
  under a full-state setpoint; otherwise the true one, which no velocity-mode controller
  reads) and the gyro (body rates in deg/s, as the IMU gives them);

then its power distribution (``powerDistribution`` and ``powerDistributionCap``) turns the
controller's output into four motor commands of 0-65535. Motors: the firmware's battery
compensation (``motors.c``) makes a command linear in thrust, 65535 being 60 g for the four
motors of a Crazyflie 2.1 (15 g, 0.147 N each); the plant's own rotor lag and its drawn motor
mismatch and battery sag act on that. The firmware's motor order is m1 front right, m2 back
right, m3 back left, m4 front left (x forward, y left), m1 and m3 turning clockwise seen from
above; ``Quadrotor``'s rotors are front left, front right, back right, back left.
"""

from __future__ import annotations

import importlib
import math
from types import ModuleType
from typing import Any

import numpy as np
from numpy.typing import NDArray

from perchpose.errors import VehicleConfigError
from perchpose.geometry import quaternion_xyzw, roll_pitch_rad, rot_z, yaw_rad
from perchpose.io.crazyflie import HOVER_THRUST, velocity_kp_deg
from perchpose.sim.firmware_params import VelocityGains
from perchpose.sim.quadrotor import (
    GRAVITY_MPS2,
    AttitudeHold,
    Hold,
    OnboardGains,
    PositionHold,
    Quadrotor,
    QuadrotorParams,
    Vec3,
)

Array = NDArray[np.float64]

FLIGHT_CONTROLLERS = (
    "model",
    "crazyflie-pid",
    "crazyflie-mellinger",
    "crazyflie-brescianini",
    "crazyflie-lee",
)
MAIN_LOOP_HZ = 1000  # the firmware's stabilizer loop
FULL_COMMAND = 65535  # a motor command at full
FULL_THRUST_N = 0.060 * GRAVITY_MPS2 / 4  # per motor at FULL_COMMAND (60 g for the four)
SETTLE_S = 10.0  # hovering before a run, for the firmware's integrators to find the hover
# motors-off ticks before a vehicle's first step: the PID's filters, which keep their state in
# the module between vehicles, run down to nothing on them
RESTING_TICKS = 10_000
# Quadrotor's rotor (front left, front right, back right, back left) driven by m1..m4
ROTOR_OF_MOTOR = (1, 2, 3, 0)
INSTALL = "../shared/firmware/install-cffirmware .venv/bin/python"
# the controllers the pilot flies; Mellinger and Lee hold thrust only on a
# position setpoint (modeAbs), Brescianini is not verified on velocity ones: they need the
# full-state commands the pilot does not send yet
VELOCITY_CONTROLLERS = ("model", "crazyflie-pid")


def load_firmware() -> ModuleType:
    """The ``cffirmware`` module, or a ``VehicleConfigError`` saying how to build it."""
    try:
        module = importlib.import_module("cffirmware")
    except ImportError as exc:
        raise VehicleConfigError(
            "the Crazyflie firmware's controllers need its Python module cffirmware, which is "
            f"not installed: build it with `{INSTALL}` (GPL-3.0, an optional extra)"
        ) from exc
    return module


def check_flight_controller(name: str) -> None:
    """Refuse a controller that is not the firmware's, or that the pilot cannot fly."""
    if name not in FLIGHT_CONTROLLERS:
        raise VehicleConfigError(
            f"unknown flight controller {name!r} (choose {', '.join(FLIGHT_CONTROLLERS)})"
        )
    if name not in VELOCITY_CONTROLLERS:
        raise VehicleConfigError(
            f"{name} holds thrust only on position setpoints (--command full-state), and on "
            "them it does not hold this 39 g vehicle's height (its thrust feed-forward takes "
            "the firmware's own mass): fly crazyflie-pid, the firmware's default controller"
        )


class _Controller:
    """One of the firmware's controllers behind one call: ``run(control, setpoint, sensors,
    state, tick)``. The PID and Brescianini controllers keep their state in the module (one
    vehicle per process at a time, which is how campaigns fly); Mellinger and Lee in a struct
    of their own."""

    def __init__(self, fw: ModuleType, name: str) -> None:
        self.name = name
        self._fw = fw
        self._self: Any = None
        if name == "crazyflie-pid":
            fw.controllerPidInit()
        elif name == "crazyflie-brescianini":
            fw.controllerBrescianiniInit()
        elif name == "crazyflie-mellinger":
            self._self = fw.controllerMellinger_t()
            fw.controllerMellingerInit(self._self)
        elif name == "crazyflie-lee":
            self._self = fw.controllerLee_t()
            fw.controllerLeeInit(self._self)
        else:
            raise VehicleConfigError(f"{name!r} is not one of the firmware's controllers")

    def start(self, state: Any) -> None:
        """Start from rest, as after a power-up, whatever an earlier vehicle in this process
        left in the module. The PID keeps its integrators, filters, desired attitude and last
        setpoint mode in static variables that ``controllerPidInit`` does not reset after the
        first call (Brescianini its last 100 Hz output): ``RESTING_TICKS`` with the motors off
        (a zero setpoint: every mode off, no thrust) take the PID through its own motors-off
        path, which resets its PIDs and takes the desired yaw from ``state`` on every tick,
        while its filters run down on a still input; the first real setpoint then changes the
        mode, which resets it once more on the vehicle's state. Mellinger's and Lee's state is
        in their own struct, made afresh."""
        if self._self is not None:
            return
        fw = self._fw
        control, setpoint, sensors = fw.control_t(), fw.setpoint_t(), fw.sensorData_t()
        for tick in range(1, RESTING_TICKS + 1):
            self.run(control, setpoint, sensors, state, tick)

    def run(self, control: Any, setpoint: Any, sensors: Any, state: Any, tick: int) -> None:
        fw = self._fw
        if self.name == "crazyflie-pid":
            fw.controllerPid(control, setpoint, sensors, state, tick)
        elif self.name == "crazyflie-brescianini":
            fw.controllerBrescianini(control, setpoint, sensors, state, tick)
        elif self.name == "crazyflie-mellinger":
            fw.controllerMellinger(self._self, control, setpoint, sensors, state, tick)
        else:
            fw.controllerLee(self._self, control, setpoint, sensors, state, tick)


class FirmwareQuadrotor(Quadrotor):
    """A ``Quadrotor`` whose onboard loops are the Crazyflie firmware's ``controller``, at
    ``physics_hz`` (a divisor of the firmware's 1 kHz)."""

    def __init__(
        self,
        controller: str,
        physics_hz: float,
        params: QuadrotorParams | None = None,
        gains: OnboardGains | None = None,
        p_m: Array | None = None,
    ) -> None:
        super().__init__(params, gains, p_m)
        ticks = MAIN_LOOP_HZ / physics_hz
        if abs(ticks - round(ticks)) > 1e-9 or ticks < 1:
            raise VehicleConfigError(
                f"the firmware's {MAIN_LOOP_HZ} Hz loop needs a physics rate that divides it, "
                f"got {physics_hz:g} Hz"
            )
        self.ticks_per_step = round(ticks)
        self.fw = load_firmware()
        self.controller = _Controller(self.fw, controller)
        fw = self.fw
        # a vehicle powers up with the stock gains, whatever one before it in this process set
        self._velocity_gains = VelocityGains.find(fw) if controller == "crazyflie-pid" else None
        if self._velocity_gains is not None:
            self._velocity_gains.stock()
        self._control = fw.control_t()
        self._setpoint = fw.setpoint_t()
        self._sensors = fw.sensorData_t()
        self._state = fw.state_t()
        self._uncapped = fw.motors_thrust_uncapped_t()
        self._pwm = fw.motors_thrust_pwm_t()
        self._tick = 0
        self.motor_command = (0, 0, 0, 0)  # m1..m4 after the cap, 0-65535

    @staticmethod
    def hovering_on_firmware(
        controller: str,
        physics_hz: float,
        params: QuadrotorParams,
        p_m: Array,
        yaw_rad: float,
        gains: OnboardGains | None = None,
    ) -> FirmwareQuadrotor:
        """A vehicle hovering at ``p_m`` with heading ``yaw_rad``, the firmware flying it."""
        q = FirmwareQuadrotor(controller, physics_hz, params, gains, np.asarray(p_m, np.float64))
        q.R_world_body = rot_z(yaw_rad)
        return q

    def settle(self) -> None:
        """Hover ``SETTLE_S`` on the firmware's loops, then put the vehicle back where it was,
        level and still: the firmware's velocity integrators then hold the hover as they do
        after a take-off (its PID starts from ``thrustBase``, 36000, about 33 g: a heavier
        vehicle sinks until the integral has made up the rest, which takes seconds)."""
        p_m, R = self.p_m, rot_z(self.yaw_rad)
        dt_s = 1.0 / (MAIN_LOOP_HZ / self.ticks_per_step)
        for _ in range(round(SETTLE_S / dt_s)):
            self.fly(dt_s, 1, np.zeros(3), 0.0, self.v_mps)
        self.p_m, self.R_world_body = p_m, R
        self.v_mps, self.omega_rad_s = np.zeros(3), np.zeros(3)

    def set_velocity_gain(self, gain_per_s: float | None) -> bool:
        """The firmware's velocity PID gains (``velCtlPid.vxKp`` and ``vyKp``, parameters a
        pilot sets over a Crazyflie's link) set to ``gain_per_s`` as the link converts it,
        written where the firmware's parameter system writes them; None puts back the stock
        gain. False where the bindings' build does not let them be found
        (``firmware_params``): the pilot then flies the stock gain, and says so."""
        if self._velocity_gains is None:
            return gain_per_s is None
        if gain_per_s is None:
            self._velocity_gains.stock()
        else:
            self._velocity_gains.set(velocity_kp_deg(gain_per_s))
        return True

    def _integrate_errors(self, dt_s: float, v_sp: Any, v_est: Any) -> None:
        """The firmware's own PIDs integrate; the model's integrals stay unused."""

    def _motor_commands(
        self, v_sp: tuple[float, float, float], yaw_rate_sp: float, v_est: Any
    ) -> tuple[float, float, float, float]:
        fw = self.fw
        sp = self._setpoint
        if self.hold is None:
            sp.mode.x = sp.mode.y = sp.mode.z = fw.modeVelocity
            sp.velocity.x, sp.velocity.y, sp.velocity.z = (float(v) for v in v_sp)
            sp.mode.yaw = fw.modeVelocity
            sp.mode.quat = fw.modeDisable
            # each packet is decoded onto a cleared setpoint: nothing of an attitude one stays
            sp.mode.roll = sp.mode.pitch = fw.modeDisable
            sp.attitude.roll = sp.attitude.pitch = 0.0
            sp.attitudeRate.yaw = math.degrees(yaw_rate_sp)
        elif isinstance(self.hold, AttitudeHold):
            self._zdistance(self.hold)
        else:
            self._full_state(self.hold)
        sp.velocity_body = False
        self._fill_state(v_est)
        if self._tick == 0:
            self.controller.start(self._state)
        for _ in range(self.ticks_per_step):
            self._tick += 1
            self.controller.run(self._control, sp, self._sensors, self._state, self._tick)
        fw.powerDistribution(self._control, self._uncapped)
        fw.powerDistributionCap(self._uncapped, self._pwm)
        m = self._pwm.motors
        self.motor_command = (int(m.m1), int(m.m2), int(m.m3), int(m.m4))
        thrust = [0.0, 0.0, 0.0, 0.0]
        for motor, rotor in enumerate(ROTOR_OF_MOTOR):
            thrust[rotor] = self.motor_command[motor] / FULL_COMMAND * FULL_THRUST_N
        return (thrust[0], thrust[1], thrust[2], thrust[3])

    def _position_loop(self, hold: Hold, v_est: Vec3) -> tuple[Vec3, float]:
        """The firmware runs its own position loop on the full-state setpoint
        (``_full_state``) and its own height loop on the attitude one (``_zdistance``):
        nothing for the model's loops to fly."""
        return (0.0, 0.0, 0.0), 0.0

    def _zdistance(self, hold: AttitudeHold) -> None:
        """The setpoint as the commander decodes cflib's ``send_zdistance_setpoint``
        (``TYPE_ZDISTANCE``): the height absolute, roll and pitch absolute in degrees (the
        pitch in the firmware's legacy sign, positive nose up, as the decoder passes it on),
        the yaw rate in velocity mode (counter-clockwise, deg/s); x and y disabled, which
        makes the PID take roll and pitch from the setpoint instead of its velocity loop."""
        fw = self.fw
        sp = self._setpoint
        sp.mode.x = sp.mode.y = fw.modeDisable
        sp.mode.z = fw.modeAbs
        sp.position.x = sp.position.y = 0.0
        sp.position.z = hold.z_m
        sp.thrust = 0.0
        if hold.thrust_fraction is not None:
            # cflib's legacy ``send_setpoint`` (``TYPE_LEGACY``): the thrust as it comes, in
            # the motors' units as the link makes it, with the height loop off (the PID
            # passes it on)
            sp.mode.z = fw.modeDisable
            sp.position.z = 0.0
            sp.thrust = hold.thrust_fraction * HOVER_THRUST
        sp.velocity.x = sp.velocity.y = sp.velocity.z = 0.0
        sp.acceleration.x = sp.acceleration.y = sp.acceleration.z = 0.0
        sp.mode.roll = sp.mode.pitch = fw.modeAbs
        sp.attitude.roll = math.degrees(hold.roll_rad)
        sp.attitude.pitch = -math.degrees(hold.pitch_rad)
        sp.mode.yaw = fw.modeVelocity
        sp.mode.quat = fw.modeDisable
        sp.attitudeRate.roll = sp.attitudeRate.pitch = 0.0
        sp.attitudeRate.yaw = math.degrees(hold.yaw_rate_rad_s)

    def _full_state(self, hold: PositionHold) -> None:
        """The setpoint as the commander decodes cflib's ``send_full_state_setpoint``
        (``TYPE_FULL_STATE``): position, velocity and acceleration (none) absolute on every
        axis, the yaw from the orientation's quaternion, roll, pitch and yaw modes disabled.
        The firmware's PID flies the position (its velocity setpoint is the position loop's
        output); Mellinger and Lee also take the velocity as a feed-forward."""
        fw = self.fw
        sp = self._setpoint
        sp.mode.x = sp.mode.y = sp.mode.z = fw.modeAbs
        sp.position.x, sp.position.y, sp.position.z = hold.p_m
        sp.velocity.x, sp.velocity.y, sp.velocity.z = hold.v_mps
        sp.acceleration.x = sp.acceleration.y = sp.acceleration.z = 0.0
        sp.mode.roll = sp.mode.pitch = sp.mode.yaw = fw.modeDisable
        sp.mode.quat = fw.modeAbs
        q = sp.attitudeQuaternion
        q.x, q.y = 0.0, 0.0
        q.z, q.w = math.sin(hold.yaw_rad / 2.0), math.cos(hold.yaw_rad / 2.0)
        sp.attitudeRate.roll = sp.attitudeRate.pitch = sp.attitudeRate.yaw = 0.0

    def _fill_state(self, v_est: Any) -> None:
        """The state estimate and the gyro as the firmware's controllers read them."""
        R = self.R_estimate
        roll, pitch = roll_pitch_rad(R)
        st = self._state
        st.attitude.roll = math.degrees(roll)
        st.attitude.pitch = -math.degrees(pitch)  # the firmware's legacy sign
        st.attitude.yaw = math.degrees(yaw_rad(R))
        qx, qy, qz, qw = quaternion_xyzw(R)
        q = st.attitudeQuaternion
        q.x, q.y, q.z, q.w = float(qx), float(qy), float(qz), float(qw)
        # a full-state setpoint is flown on the vehicle's own position estimate; velocity
        # setpoints never read it (the true position keeps the state whole)
        p_m = self.p_m if self.hold is None else self._p_estimate
        st.position.x, st.position.y, st.position.z = (float(v) for v in p_m)
        st.velocity.x, st.velocity.y, st.velocity.z = (float(v) for v in v_est)
        wx, wy, wz = (math.degrees(float(w)) for w in self.omega_rad_s)
        g = self._sensors.gyro
        g.x, g.y, g.z = wx, wy, wz

import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from perchpose.io.crazyflie import velocity_kp_deg
from perchpose.sim import firmware_params
from perchpose.sim.firmware import FirmwareQuadrotor
from perchpose.sim.firmware_params import STOCK_GAINS, VelocityGains
from perchpose.sim.quadrotor import QuadrotorParams

DT = 1 / 500


def _rise_time_s(q: FirmwareQuadrotor, v_mps: float = 0.5) -> float:
    """Time for the vehicle to reach 63 % of a velocity step along x."""
    for i in range(1, 1001):
        q.fly(DT, 1, np.array([v_mps, 0.0, 0.0]), 0.0, q.v_mps)
        if q.v_mps[0] > 0.63 * v_mps:
            return i * DT
    raise AssertionError("the step was never followed")


def _hovering() -> FirmwareQuadrotor:
    q = FirmwareQuadrotor.hovering_on_firmware(
        "crazyflie-pid", 500.0, QuadrotorParams(), np.array([0.0, 0.0, 1.0]), 0.0
    )
    q.settle()
    return q


def test_the_velocity_gains_are_found_where_the_parameter_system_keeps_them() -> None:
    fw = pytest.importorskip("cffirmware")
    gains = VelocityGains.find(fw)
    assert gains is not None
    gains.stock()
    assert gains.kp_deg() == (STOCK_GAINS[0], STOCK_GAINS[0])
    gains.set(35.0)
    again = VelocityGains.find(fw)  # a gain we left is still recognised as the same floats
    assert again is not None
    assert again.kp_deg() == pytest.approx((35.0, 35.0))
    again.stock()
    assert gains.kp_deg() == (25.0, 25.0)


def test_a_raised_gain_is_flown_and_the_next_vehicle_powers_up_stock() -> None:
    """The pilot's 6 /s reaches the firmware's velocity PID as cflib's param write would
    (35 deg per m/s): the vehicle follows a step faster; a vehicle made after it in the same
    process starts from the stock 25, as a Crazyflie after a power cycle."""
    pytest.importorskip("cffirmware")
    stock_rise_s = _rise_time_s(_hovering())
    q = _hovering()
    assert q.set_velocity_gain(6.0)
    assert q._velocity_gains is not None
    assert q._velocity_gains.kp_deg() == pytest.approx((velocity_kp_deg(6.0),) * 2, abs=1e-4)
    raised_rise_s = _rise_time_s(q)
    assert raised_rise_s < 0.9 * stock_rise_s
    fresh = _hovering()
    assert fresh._velocity_gains is not None
    assert fresh._velocity_gains.kp_deg() == (25.0, 25.0)
    assert q.set_velocity_gain(None)
    assert q._velocity_gains.kp_deg() == (25.0, 25.0)


def test_a_stripped_extension_keeps_its_stock_gains(tmp_path: Path) -> None:
    """Without a symbol table the struct cannot be found for sure: refused, never written at
    a guessed address (the pilot then flies the stock gain and says so)."""
    fw = pytest.importorskip("cffirmware")
    strip = shutil.which("strip")
    if strip is None:
        pytest.skip("no strip(1) on this machine")
    original = Path(fw._cffirmware.__file__)
    stripped = tmp_path / original.name
    subprocess.run([strip, "-o", str(stripped), str(original)], check=True)
    assert firmware_params._struct_after_anchor(str(stripped)) is None
    assert firmware_params._struct_after_anchor(str(original)) is not None
    not_elf = tmp_path / "notes.txt"
    not_elf.write_text("not an extension")
    assert firmware_params._struct_after_anchor(str(not_elf)) is None


def test_floats_that_do_not_hold_the_stock_gains_are_refused(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A build whose struct is laid out otherwise is caught by what the floats hold."""
    fw = pytest.importorskip("cffirmware")
    monkeypatch.setattr(firmware_params, "KP_OFFSET", 0)  # the PID's `desired`, not its kp
    assert VelocityGains.find(fw) is None

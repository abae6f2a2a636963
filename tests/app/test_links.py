import time

import pytest

from perchpose.app.links import LinkOptions, vehicle_links
from perchpose.errors import ControllerConfigError
from perchpose.io.mavlink.landing_target_sink import mavutil_module
from perchpose.target import TargetSpec
from perchpose.values import Estimate


def test_no_options_open_no_link() -> None:
    said: list[str] = []
    with vehicle_links(TargetSpec.paper(), LinkOptions(), said.append) as links:
        assert links.hooks == []
        assert links.controllers == []
        assert links.time_offset() is None
    assert said == []


@pytest.mark.parametrize("flag", ["mavlink_pilot", "crazyflie"])
def test_a_pilot_refuses_a_downward_camera_before_any_link_opens(flag: str) -> None:
    options = (
        LinkOptions(mavlink_url="udpout:127.0.0.1:9", mavlink_pilot=True, mount="down")
        if flag == "mavlink_pilot"
        else LinkOptions(crazyflie_uri="radio://0/80/2M/E7E7E7E7E7", mount="down")
    )
    with (
        pytest.raises(ControllerConfigError, match="camera must look up"),
        vehicle_links(TargetSpec.paper(), options, print),
    ):
        pass


def test_landing_target_goes_out_and_the_link_closes(udp_port: int) -> None:
    vehicle = mavutil_module().mavlink_connection(f"udpin:127.0.0.1:{udp_port}")
    options = LinkOptions(mavlink_url=f"udpout:127.0.0.1:{udp_port}", mount="down")
    try:
        with vehicle_links(TargetSpec.paper(), options, print) as links:
            hooks = links.hooks
            assert len(hooks) == 1
            assert links.controllers == []  # LANDING_TARGET informs; no controller flies
            for k in range(5):
                estimate = Estimate.of_pose(0.1 * k, (0.01, -0.02, 0.5), 0.3)
                hooks[0](estimate, 0.1 * k)
                time.sleep(0.05)
        received = []
        deadline = time.monotonic() + 2.0
        while time.monotonic() < deadline and len(received) < 5:
            msg = vehicle.recv_match(type="LANDING_TARGET", blocking=True, timeout=0.1)
            if msg is not None:
                received.append(msg)
        assert len(received) == 5
        assert received[0].distance == pytest.approx(0.5, abs=0.01)
    finally:
        vehicle.close()


def test_the_end_of_a_flight_says_the_fixes_given_to_the_vehicle() -> None:
    import numpy as np

    from perchpose.app.links import VehicleLinks
    from perchpose.control import ControllerSettings, PerchingController
    from perchpose.control.position_fix import PositionFixSettings

    said: list[str] = []
    quiet = VehicleLinks(controllers=[PerchingController()])
    quiet.say_fixes(said.append)
    assert said == []  # nothing made, nothing said
    settings = ControllerSettings(position_fixes=PositionFixSettings(anchor_fixes=1))
    controller = PerchingController(settings)
    for target in ([0.0, 0.0, 2.0], [0.01, 0.0, 2.0], [0.5, 0.0, 2.0]):
        controller.position_fixes.fix(np.array(target), np.zeros(3))
    VehicleLinks(controllers=[controller]).say_fixes(said.append)
    assert said == [
        "position fixes for the vehicle's estimator: 1 made, 1 held back as over 0.1 m aside "
        "from its own estimate"
    ]

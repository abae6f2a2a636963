from pathlib import Path

import numpy as np
import pytest
import yaml

from perchpose.control import (
    default_T_body_camera,
    downward_T_body_camera,
    mount_T_body_camera,
)
from perchpose.errors import ControllerConfigError


def test_presets_look_up_and_down() -> None:
    up, down = mount_T_body_camera("up"), mount_T_body_camera("down")
    assert np.array_equal(up, default_T_body_camera())
    assert np.array_equal(down, downward_T_body_camera())
    R = down[:3, :3]
    assert np.allclose(R @ R.T, np.eye(3))
    assert np.linalg.det(R) == pytest.approx(1.0)
    # optical axis along the body's -z; the image's top (camera -y) toward the body's front
    assert np.allclose(R[:, 2], [0.0, 0.0, -1.0])
    assert np.allclose(-R[:, 1], [1.0, 0.0, 0.0])
    assert down[2, 3] < 0 < up[2, 3]


def test_a_mount_file_or_a_clear_error(tmp_path: Path) -> None:
    path = tmp_path / "mount.yaml"
    T = downward_T_body_camera()
    path.write_text(yaml.safe_dump({"T_body_camera": T.tolist()}))
    assert np.allclose(mount_T_body_camera(str(path)), T)
    with pytest.raises(ControllerConfigError, match=r"sideways\.yaml: cannot read"):
        mount_T_body_camera(str(tmp_path / "sideways.yaml"))
    binary = tmp_path / "mount.bin"
    binary.write_bytes(bytes(range(256)))
    with pytest.raises(ControllerConfigError, match=r"mount\.bin: not a text file"):
        mount_T_body_camera(str(binary))

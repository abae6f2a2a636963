"""Settings files that would hang or exhaust the process (an alias bomb expanding to
gigabytes, nesting that exhausts the recursion, a huge file) are one clear error naming the
file, refused while parsing."""

from pathlib import Path

import pytest

from perchpose import CameraModel, TargetSpec
from perchpose.cli import main
from perchpose.control import load_T_body_camera
from perchpose.errors import CameraFileError, ControllerConfigError, TargetSpecError

BOMB = "\n".join(
    ["a: &a ['lol', 'lol', 'lol', 'lol', 'lol', 'lol', 'lol', 'lol', 'lol']"]
    + [f"{chr(98 + i)}: &{chr(98 + i)} [{', '.join(['*' + chr(97 + i)] * 9)}]" for i in range(8)]
)
DEEP = "camera_matrix: " + "[" * 100_000 + "]" * 100_000


@pytest.mark.parametrize(
    ("text", "message"),
    [
        (BOMB, "aliases expand to over 100,000 values"),
        (DEEP, "nested over 64 levels"),
        ("a: " + "x" * 1_100_000, "over 1 MB"),
    ],
)
def test_hostile_yaml_is_refused_quickly(tmp_path: Path, text: str, message: str) -> None:
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    for load, error in (
        (CameraModel.load, CameraFileError),
        (TargetSpec.load, TargetSpecError),
        (load_T_body_camera, ControllerConfigError),
    ):
        with pytest.raises(error, match=r"bad\.yaml") as caught:
            load(path)
        assert message in str(caught.value)


def test_the_cli_says_it_in_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], approach_fpv_dir: Path
) -> None:
    camera = tmp_path / "camera.yaml"
    camera.write_text(DEEP)
    code = main(["track", str(approach_fpv_dir), "--camera", str(camera), "--out", "x.csv"])
    err = capsys.readouterr().err
    assert code == 2
    assert err.count("\n") == 1
    assert "camera.yaml" in err
    assert "nested over 64 levels" in err
    assert "Traceback" not in err

import contextlib
import importlib
import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from perchpose import CameraModel
from perchpose.cli import main
from perchpose.io.sinks import read_track_csv
from perchpose.sim.lossy_video import encode_h264, lose_packets


@pytest.fixture(scope="module")
def short_sequence(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("cli") / "seq"
    assert (
        main(
            [
                "simulate",
                "approach",
                "--camera",
                "preset:webcam",
                "--out",
                str(out),
                "--frames",
                "6",
            ]
        )
        == 0
    )
    return out


def _run(args: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    code = main(args)
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def _single_error_line(err: str) -> str:
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1, err
    assert "Traceback" not in err
    return lines[0]


def test_simulate_writes_a_sequence(short_sequence: Path) -> None:
    assert len(list(short_sequence.glob("frame_*.png"))) == 6
    assert (short_sequence / "truth.csv").is_file()


def test_track_csv_jsonl_and_overlay(
    short_sequence: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    camera = str(short_sequence / "camera.yaml")
    code, out, _ = _run(
        [
            "track",
            str(short_sequence),
            "--camera",
            camera,
            "--out",
            str(tmp_path / "p.csv"),
            "--overlay",
            str(tmp_path / "o.mp4"),
        ],
        capsys,
    )
    assert code == 0
    assert "6 frames, 6 valid" in out
    assert len(read_track_csv(tmp_path / "p.csv")) == 6
    assert (tmp_path / "o.mp4").stat().st_size > 1000
    code, _, _ = _run(
        [
            "track",
            str(short_sequence / "frame_*.png"),
            "--camera",
            camera,
            "--out",
            str(tmp_path / "p.jsonl"),
            "--fps",
            "15",
        ],
        capsys,
    )
    assert code == 0
    assert len((tmp_path / "p.jsonl").read_text().splitlines()) == 6


def test_target_command(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code, out, _ = _run(
        ["target", "--out", str(tmp_path / "t.svg"), "--save-spec", str(tmp_path / "t.yaml")],
        capsys,
    )
    assert code == 0
    assert "scale bar" in out
    assert (tmp_path / "t.yaml").is_file()
    code, _, _ = _run(
        ["target", "--out", str(tmp_path / "t2.pdf"), "--target", str(tmp_path / "t.yaml")], capsys
    )
    assert code == 0


def test_corrupt_frame_does_not_stop_the_run(
    short_sequence: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    frames = tmp_path / "frames"
    frames.mkdir()
    for p in sorted(short_sequence.glob("frame_*.png")):
        (frames / p.name).write_bytes(p.read_bytes())
    (frames / "frame_000002.png").write_bytes(b"not a png")
    code, _, err = _run(
        [
            "track",
            str(frames),
            "--camera",
            str(short_sequence / "camera.yaml"),
            "--out",
            str(tmp_path / "p.csv"),
        ],
        capsys,
    )
    assert code == 0
    assert "frame_000002.png: cannot read image" in _single_error_line(err)
    rows = read_track_csv(tmp_path / "p.csv")
    assert [r["valid"] for r in rows] == ["1", "1", "0", "1", "1", "1"]
    assert rows[2]["frame"] == "2"


def test_a_folder_of_nothing_but_unreadable_images_exits_non_zero(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Every frame's row is written with its reason, and the run says that none was read."""
    frames = tmp_path / "frames"
    frames.mkdir()
    for k in range(3):
        (frames / f"frame_{k}.png").write_bytes(b"not a png")
    out = tmp_path / "p.csv"
    code, _, err = _run(
        ["track", str(frames), "--camera", "preset:webcam", "--out", str(out)], capsys
    )
    assert code == 2
    assert f"perchpose: error: {frames}: none of its 3 frames could be read" in err
    assert "Traceback" not in err
    assert len(read_track_csv(out)) == 3


def test_a_lossy_video_says_which_frames_it_did_not_measure(
    short_sequence: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Six frames as H.264 with frame 2's packet lost: frames 3-5 are predicted from it; the
    run says so once, goes on, and its closing line counts them."""
    import cv2

    images = (cv2.imread(str(p)) for p in sorted(short_sequence.glob("frame_*.png")))
    clean = encode_h264(images, tmp_path / "clean.mp4", gop=6)
    lossy = lose_packets(clean, tmp_path / "lossy.mp4", drop={2}, zero_half=set())
    camera = str(short_sequence / "camera.yaml")
    code, out, err = _run(
        ["track", str(lossy), "--camera", camera, "--out", str(tmp_path / "p.csv")], capsys
    )
    assert code == 0
    warnings = err.strip().splitlines()
    assert len(warnings) == 2
    assert "frame 2 cannot be decoded" in warnings[0]
    assert "frame 3 is predicted from damaged or missing frames" in warnings[1]
    assert "6 frames, 2 valid" in out
    assert "1 unreadable, 3 damaged (decoded from damaged data, not measured)" in out
    rows = read_track_csv(tmp_path / "p.csv")
    assert [r["valid"] for r in rows] == ["1", "1", "0", "0", "0", "0"]
    assert all("not measured" in r["error"] for r in rows[3:])


def _bad_camera(tmp_path: Path, kind: str) -> Path:
    path = tmp_path / "cam.yaml"
    data = CameraModel.preset("webcam").to_ros_dict()
    if kind == "missing":
        return tmp_path / "nope.yaml"
    if kind == "unparsable":
        path.write_text("image_width: [640\n")
        return path
    if kind == "field":
        del data["camera_matrix"]
    if kind == "size":
        data["image_width"], data["image_height"] = 320, 240
    path.write_text(yaml.safe_dump(data))
    return path


@pytest.mark.parametrize(
    ("kind", "message"),
    [
        ("missing", "nope.yaml: camera file not found"),
        ("unparsable", "cam.yaml: not valid YAML"),
        ("field", "cam.yaml: missing field 'camera_matrix'"),
        ("size", "frame_000000.png: image is 640x480 but camera"),
    ],
)
def test_bad_camera_files_exit_2_with_one_line(
    short_sequence: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    kind: str,
    message: str,
) -> None:
    camera = _bad_camera(tmp_path, kind)
    code, _, err = _run(
        ["track", str(short_sequence), "--camera", str(camera), "--out", str(tmp_path / "p.csv")],
        capsys,
    )
    assert code == 2
    line = _single_error_line(err)
    assert line.startswith("perchpose: error: ")
    assert message in line


def test_bad_sources_and_outputs_exit_2(
    short_sequence: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    camera = str(short_sequence / "camera.yaml")
    empty = tmp_path / "empty"
    empty.mkdir()
    cases = [
        (
            ["track", str(empty), "--camera", camera, "--out", str(tmp_path / "p.csv")],
            "holds no image files",
        ),
        (
            ["track", str(short_sequence), "--camera", camera, "--out", str(tmp_path / "p.txt")],
            "must end in .csv, .jsonl or .mcap",
        ),
        (
            [
                "track",
                str(short_sequence),
                "--camera",
                camera,
                "--out",
                str(tmp_path / "p.csv"),
                "--fps",
                "0",
            ],
            "--fps must be a positive",
        ),
        (
            [
                "track",
                str(short_sequence),
                "--camera",
                camera,
                "--out",
                str(tmp_path / "p.csv"),
                "--budget-ms",
                "nan",
            ],
            "--budget-ms must be a positive number, got nan",
        ),
        (["simulate", "orbit", "--out", str(tmp_path / "s")], "unknown scenario 'orbit'"),
        (
            [
                "track",
                str(short_sequence),
                "--camera",
                "preset:nope",
                "--out",
                str(tmp_path / "p.csv"),
            ],
            "unknown camera preset",
        ),
    ]
    for args, message in cases:
        code, _, err = _run(args, capsys)
        assert code == 2, args
        assert message in _single_error_line(err)


def test_usage_error_exits_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code, _, err = _run(["track", "somewhere"], capsys)
    assert code == 2
    assert "--out" in err
    assert "Traceback" not in err
    # --camera may be left out only for a ROS bag, whose CameraInfo gives the camera
    code, _, err = _run(["track", str(tmp_path), "--out", str(tmp_path / "p.csv")], capsys)
    assert code == 2
    assert "--camera" in err
    assert "Traceback" not in err
    argv = ["track", str(tmp_path), "--out", "p.csv", "--realtime", "--rate", "2"]
    code, _, err = _run(argv, capsys)
    assert code == 2
    assert "--realtime is --rate 1" in err


def test_console_entry_point_reports_without_traceback(tmp_path: Path) -> None:
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "perchpose",
            "track",
            str(tmp_path / "none"),
            "--camera",
            str(tmp_path / "cam.yaml"),
            "--out",
            str(tmp_path / "p.csv"),
        ],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert proc.returncode == 2
    assert proc.stderr.strip().count("\n") == 0
    assert "camera file not found" in proc.stderr


@pytest.mark.parametrize(("signum", "code"), [(signal.SIGTERM, 143), (signal.SIGHUP, 129)])
def test_sigterm_and_sighup_end_a_run_as_ctrl_c_does(
    approach_webcam_dir: Path, tmp_path: Path, signum: int, code: int
) -> None:
    """The rows written before the signal are all in the file, whole; one line says why."""
    out = tmp_path / "p.csv"
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "perchpose",
            "track",
            str(approach_webcam_dir),
            "--camera",
            str(approach_webcam_dir / "camera.yaml"),
            "--out",
            str(out),
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and proc.poll() is None:
        if out.exists() and out.read_text().count("\n") >= 6:
            break
        time.sleep(0.05)
    assert proc.poll() is None, "the run ended before the signal"
    proc.send_signal(signum)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == code, err[-2000:]
    assert err.strip() == f"perchpose: terminated ({signal.Signals(signum).name})"
    rows = read_track_csv(out)
    assert 5 <= len(rows) < 90
    assert [r["frame"] for r in rows] == [str(k) for k in range(len(rows))]
    assert all(None not in r.values() and r["file"].endswith(".png") for r in rows)


def test_a_bad_overlay_path_is_refused_before_the_first_frame(
    short_sequence: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "p.csv"
    (tmp_path / "a-file").write_text("")
    code, _, err = _run(
        [
            "track",
            str(short_sequence),
            "--camera",
            str(short_sequence / "camera.yaml"),
            "--out",
            str(out),
            "--overlay",
            str(tmp_path / "a-file" / "run.mp4"),  # a folder that cannot be made
        ],
        capsys,
    )
    assert code == 2
    assert "cannot make the folder" in _single_error_line(err)
    assert not out.exists()  # nothing ran: no vehicle link would have been opened either


def test_track_makes_the_folders_it_writes_into(
    short_sequence: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "runs" / "today" / "p.csv"
    overlay = tmp_path / "videos" / "run.avi"
    args = ["track", str(short_sequence), "--camera", str(short_sequence / "camera.yaml")]
    code, _, _ = _run([*args, "--out", str(out), "--overlay", str(overlay)], capsys)
    assert code == 0
    assert out.stat().st_size > 0
    assert overlay.stat().st_size > 0


def test_bench_times_a_rendered_approach(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "results" / "bench.json"
    code, text, _ = _run(
        [
            "bench",
            "--camera",
            "preset:webcam",
            "--frames",
            "4",
            "--repeat",
            "1",
            "--quiet",
            "--json",
            str(out),
        ],
        capsys,
    )
    assert code == 0
    assert "opencv" in text
    assert "perchpose-cold" in text
    data = json.loads(out.read_text())
    assert data["frames"] == 4
    assert data["methods"]["perchpose"]["ratio_to_opencv"]["p50"] > 0


def test_bench_plot_is_checked_before_the_run_and_written_after_it(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    args = ["bench", "--camera", "preset:webcam", "--frames", "3", "--repeat", "1", "--quiet"]
    code, text, err = _run([*args, "--plot", str(tmp_path / "bench.jpg")], capsys)
    assert code == 2
    assert "bench.jpg" in _single_error_line(err)
    assert text == ""  # refused before any frame was timed
    plot = tmp_path / "plots" / "bench.png"
    code, text, _ = _run([*args, "--plot", str(plot)], capsys)
    assert code == 0
    assert f"wrote {plot}" in text
    assert plot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_bench_refuses_a_source_without_its_calibration(
    short_sequence: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    code, _, err = _run(["bench", str(short_sequence)], capsys)
    assert code == 2
    assert "--camera" in _single_error_line(err)
    code, _, err = _run(["bench", "--budget-ms", "0"], capsys)
    assert code == 2
    assert "--budget-ms" in err
    code, _, err = _run(
        ["bench", str(short_sequence / "missing"), "--camera", str(short_sequence / "camera.yaml")],
        capsys,
    )
    assert code == 2
    assert "missing" in _single_error_line(err)


def test_a_signal_inside_a_compiled_call_ends_the_run_as_the_signal_does(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """SIGHUP handled while numba's compiled code calls back into Python comes out of those
    calls as a chain of SystemErrors with the interrupt at its root: the run still ends with
    128 + the signal and one line, not a traceback and exit code 1."""
    main_module = importlib.import_module("perchpose.cli.main")

    def compiled_call_interrupted(*args: object, **kwargs: object) -> None:
        try:
            try:
                raise main_module.Terminated(signal.SIGHUP)
            except KeyboardInterrupt as exc:
                raise SystemError(
                    "_numba_unpickle returned a result with an exception set"
                ) from exc
        except SystemError as exc:
            raise SystemError("CPUDispatcher returned a result with an exception set") from exc

    monkeypatch.setattr(main_module.group, "main", compiled_call_interrupted)
    code, _, err = _run(["track"], capsys)
    assert code == 128 + signal.SIGHUP
    assert err.strip() == "perchpose: terminated (SIGHUP)"


def test_a_system_error_of_its_own_is_not_taken_for_a_signal(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    main_module = importlib.import_module("perchpose.cli.main")

    def broken(*args: object, **kwargs: object) -> None:
        raise SystemError("something else")

    monkeypatch.setattr(main_module.group, "main", broken)
    with pytest.raises(SystemError, match="something else"):
        main(["track"])


def test_a_signal_that_leaves_a_bare_system_error_still_ends_the_run_as_the_signal_does(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """A compiled call that the handler interrupts may hand back a SystemError whose chain
    no longer holds the interrupt: the signal the run received decides."""
    main_module = importlib.import_module("perchpose.cli.main")

    def compiled_call_interrupted(*args: object, **kwargs: object) -> None:
        with contextlib.suppress(KeyboardInterrupt):
            main_module._terminate(signal.SIGHUP, None)
        raise SystemError("CPUDispatcher returned a result with an exception set")

    monkeypatch.setattr(main_module.group, "main", compiled_call_interrupted)
    code, _, err = _run(["track"], capsys)
    assert code == 128 + signal.SIGHUP
    assert err.strip() == "perchpose: terminated (SIGHUP)"

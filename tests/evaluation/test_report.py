import json
from pathlib import Path

import numpy as np
import pytest

from perchpose.cli import main
from perchpose.evaluation.fusion_data import load_fusion_samples
from perchpose.evaluation.fusion_fit import fit_sigma_lms
from perchpose.evaluation.report import EvalPlan
from perchpose.fusion.paper import FusionSigmas
from perchpose.io.sinks import read_track_csv


# the paper's whole evaluation, flown once for the checks that read it (all ``slow``: they run
# after the suite, in CI and with ``pytest -m slow``)
@pytest.fixture(scope="module")
def quick_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("evaluate")
    assert main(["evaluate", "paper", "--quick", "--out", str(out)]) == 0
    return out


@pytest.mark.slow  # the paper's evaluation, flown whole (about 25 s)
def test_quick_run_writes_report_figures_and_results(quick_run: Path) -> None:
    for name in (
        "report.md",
        "results.json",
        "ranges.png",
        "kalman.png",
        "ablation.png",
        "fusion.png",
        "fusion_data.csv",
    ):
        assert (quick_run / name).stat().st_size > 0, name
    results = json.loads((quick_run / "results.json").read_text())
    for key in ("ranges", "table1", "table2", "fusion_fit", "dropout", "ablations", "config"):
        assert key in results
    for marker in ("outer", "inner"):
        assert set(results["ranges"][marker]) == {"z_max_cm", "z_min_cm"}
    assert results["ranges"]["outer"]["z_max_cm"] > results["ranges"]["inner"]["z_max_cm"]
    assert len(results["table1"]) == 5
    assert len(results["table2"]) == 8
    for row in results["table1"] + results["table2"]:
        assert {"actual", "estimated", "error"} <= set(row)
    # the paper's LMS, run with a small step on the run's own samples, lands on the closed-form
    # least-squares sigma (with the default step it wanders around it by a few hundredths)
    fit = results["fusion_fit"]
    data = np.genfromtxt(quick_run / "fusion_data.csv", delimiter=",", names=True)
    for axis in ("x_cm", "y_cm", "z_cm", "yaw_deg"):
        columns = [data[f"{p}_{axis}"] for p in ("m0", "m1", "true")]
        sigma, _ = fit_sigma_lms(*columns, circular=axis == "yaw_deg", step=0.02, epochs=4000)
        name = "sigma_" + axis.split("_")[0]
        assert abs(fit["least_squares"][name] - sigma) <= 0.01
        assert abs(fit["least_squares"][name] - fit["lms"][name]) <= 0.1
    assert results["dropout"]["frames_coasted"] == 8
    assert results["config"]["renders"] == EvalPlan.make(quick=True).renders()
    report = (quick_run / "report.md").read_text()
    assert "Table 1" in report
    assert "(10, 12, 7)" in report


@pytest.mark.slow  # the paper's evaluation, flown whole (about 25 s)
def test_table1_rows_in_view_meet_the_papers_bound(quick_run: Path) -> None:
    results = json.loads((quick_run / "results.json").read_text())
    measured = [r for r in results["table1"] if r["valid_frames"]]
    assert len(measured) >= 3
    for row in measured:
        assert all(abs(v) <= 0.6 for v in row["max_abs_error"][:3])
    for row in results["table2"]:
        assert abs(row["max_abs_error"][3]) <= 3.0


@pytest.mark.slow
def test_same_seed_same_numbers(quick_run: Path, tmp_path: Path) -> None:
    from perchpose.evaluation.report import run_paper_evaluation

    again = run_paper_evaluation(tmp_path, quick=True, progress=False, say=lambda _: None)
    first = json.loads((quick_run / "results.json").read_text())
    for key in ("ranges", "table1", "table2", "fusion_fit", "dropout"):
        assert again.results[key] == first[key]


@pytest.mark.slow  # the paper's evaluation, flown whole (about 25 s)
def test_fit_fusion_reads_the_evaluation_data(
    quick_run: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    samples = load_fusion_samples(quick_run / "fusion_data.csv")
    assert samples.truth.shape[1] == 4
    out = tmp_path / "fit.json"
    assert main(["fit-fusion", str(quick_run / "fusion_data.csv"), "--json", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "sigma_z" in printed
    fitted = json.loads(out.read_text())
    expected = json.loads((quick_run / "results.json").read_text())["fusion_fit"]
    # the CSV keeps 5 decimals of each measurement
    assert fitted["least_squares"] == pytest.approx(expected["least_squares"], abs=1e-3)
    # the weights are the least-squares fit under the names FusionSigmas takes, and load
    sigmas = FusionSigmas.load(out)
    assert sigmas.z == pytest.approx(fitted["least_squares"]["sigma_z"])
    assert all(0.0 <= v <= 1.0 for v in sigmas.to_dict().values())


@pytest.mark.slow  # the paper's evaluation, flown whole (about 25 s)
def test_fitted_weights_fly_in_track(
    quick_run: Path, approach_fpv_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """fit-fusion's JSON goes straight into track --sigmas, which fuses with the paper's
    fusion and those weights; a bad weights file is one line and exit code 2."""
    fit = tmp_path / "fit.json"
    assert main(["fit-fusion", str(quick_run / "fusion_data.csv"), "--json", str(fit)]) == 0
    assert "--sigmas" in capsys.readouterr().out
    camera = str(approach_fpv_dir / "camera.yaml")
    args = ["track", str(approach_fpv_dir), "--camera", camera, "--quiet"]
    assert main([*args, "--out", str(tmp_path / "fitted.csv"), "--sigmas", str(fit)]) == 0
    assert main([*args, "--out", str(tmp_path / "joint.csv")]) == 0
    fitted = read_track_csv(tmp_path / "fitted.csv")
    default = read_track_csv(tmp_path / "joint.csv")
    assert len(fitted) == len(default) > 60
    assert sum(r["valid"] == "1" for r in fitted) > 60
    # stage 2 frames fuse both markers with other weights than the joint pose: they differ
    both = [(a, b) for a, b in zip(fitted, default, strict=True) if a["stage"] == "2"]
    assert any(a["z_cm"] != b["z_cm"] for a, b in both)
    capsys.readouterr()
    bad = tmp_path / "bad.json"
    bad.write_text('{"x": 0.3, "y": 0.4, "z": 1.5, "yaw": 0.5}')
    assert main([*args, "--out", str(tmp_path / "bad.csv"), "--sigmas", str(bad)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1
    assert str(bad) in err[0]


def test_fit_fusion_on_a_track_file_asks_for_the_truth(
    approach_fpv_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    poses = tmp_path / "poses.csv"
    camera = str(approach_fpv_dir / "camera.yaml")
    assert (
        main(["track", str(approach_fpv_dir), "--camera", camera, "--quiet", "--out", str(poses)])
        == 0
    )
    assert main(["fit-fusion", str(poses)]) == 2
    assert "--truth" in capsys.readouterr().err
    truth = str(approach_fpv_dir / "truth.csv")
    assert main(["fit-fusion", str(poses), "--truth", truth]) == 0


def test_fit_fusion_bad_input(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "d.csv"
    path.write_text("true_x_cm,m0_x_cm\n1,2\n")
    assert main(["fit-fusion", str(path)]) == 2
    assert "missing column" in capsys.readouterr().err
    assert main(["fit-fusion", str(tmp_path / "none.csv")]) == 2
    assert "file not found" in capsys.readouterr().err

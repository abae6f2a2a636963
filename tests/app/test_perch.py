import json
from pathlib import Path

import pytest

from perchpose.app.inputs import load_camera
from perchpose.app.perch import PerchCampaign, PerchOptions, run
from perchpose.errors import PerchposeError


def test_a_campaign_as_a_library_call(tmp_path: Path) -> None:
    """``run`` flies the runs asked for and writes the reports and the summary JSON; the
    JSON returned is the one written. Unless asked otherwise the pilot sends attitude
    setpoints, what perches best with the Crazyflie firmware in the loop."""
    out = tmp_path / "perch"
    said: list[str] = []
    options = PerchOptions(
        str(out),
        estimators="truth",
        runs=2,
        seed=7,
        sensing="ideal",
        json_out=str(tmp_path / "summary.json"),
        workers=1,
    )
    content = run(options, say=said.append)
    assert content["runs"] == 2
    assert content["estimator"] == "truth"
    assert content["command"] == "attitude"
    assert json.loads((tmp_path / "summary.json").read_text())["runs"] == 2
    rows = (out / "runs.csv").read_text().splitlines()
    assert len(rows) == 3  # header and two runs
    assert any("2 runs" in line for line in said)


def test_an_unknown_estimator_is_named(tmp_path: Path) -> None:
    with pytest.raises(PerchposeError, match=r"--estimator: unknown.*nope"):
        run(PerchOptions(str(tmp_path), estimators="truth,nope", runs=1))
    assert not (tmp_path / "runs.csv").exists()


@pytest.mark.parametrize(
    ("command", "said_as"),
    [("full-state", "full-state setpoints"), ("attitude", "attitude setpoints (a lean")],
)
def test_a_campaign_flown_on_other_setpoints_says_so(
    tmp_path: Path, command: str, said_as: str
) -> None:
    """``command="full-state"``: the pilot sends positions the vehicle's position loop holds;
    ``"attitude"``: a lean and a height, the pilot flying the velocity loop itself. A run
    perches in still air with the true pose, and the reports say which command flew."""
    out = tmp_path / "perch"
    said: list[str] = []
    options = PerchOptions(str(out), estimators="truth", runs=1, seed=3, workers=1, command=command)
    content = run(options, say=said.append)
    assert content["command"] == command
    assert content["setup"]["command"] == command
    assert content["success_rate"] == 1.0
    assert any(said_as in line for line in said)
    with pytest.raises(PerchposeError, match="--command: unknown 'thrust'"):
        run(PerchOptions(str(tmp_path / "other"), estimators="truth", runs=1, command="thrust"))


def test_a_runs_length_is_asked_for_and_recorded(tmp_path: Path) -> None:
    """``duration_s``: every run may fly that long and no longer (from 60-150 cm below the
    target at up to 0.3 m/s, 1.5 s is too short to perch); the reports say how long it was,
    and how long each vehicle hovered before it (``hover_s``). Without it a run has 20 s, 40 s
    with faults."""
    options = PerchOptions(
        str(tmp_path / "short"),
        estimators="truth",
        runs=1,
        seed=7,
        sensing="ideal",
        workers=1,
        duration_s=1.5,
        hover_s=0.5,
    )
    content = run(options, say=lambda _: None)
    assert content["duration_s"] == 1.5
    setup = content["setup"]
    assert isinstance(setup, dict)
    assert setup["duration_s"] == 1.5
    assert setup["hover_s"] == 0.5
    assert content["success_rate"] == 0.0
    cell = next(iter(content["cells"].values()))
    assert isinstance(cell, dict)
    assert cell["reasons"] == {"timeout": 1}
    default = PerchCampaign.from_options(load_camera("preset:fpv"), estimators="truth", runs=1)
    faulty = PerchCampaign.from_options(
        load_camera("preset:fpv"), estimators="truth", runs=1, faults="link-loss"
    )
    assert default.setups[0].duration_s == 20.0
    assert faulty.setups[0].duration_s == 40.0


def test_the_table_says_where_the_magnet_did_not_hold_and_leans_were_refused() -> None:
    """A cell with checks of the magnet's hold the vehicle came down in gets its own line
    under the table; a cell without gets none."""
    from dataclasses import replace

    from perchpose import CameraModel, TargetSpec
    from perchpose.app.perch import summary_table
    from perchpose.evaluation.perching import RunRecord, summary_json
    from perchpose.sim.perch import PerchSetup

    setup = PerchSetup(CameraModel.preset("fpv"), TargetSpec.paper(), estimator="truth")
    base = RunRecord("truth", "light", 1.5, 0.5, 0, True, "perched", 3.0, 0.2, 5.0, 0, 90.0, "33")
    quiet = summary_table(summary_json([base, replace(base, seed=1)], setup))
    assert "did not hold" not in quiet
    records = [replace(base, seat_drops=2), replace(base, seed=1, leans_refused=True)]
    table = summary_table(summary_json(records, setup))
    assert "the magnet did not hold the vehicle in 2 checks before a stop, in 1 runs" in table
    assert "did not fly the leans sent in 1 runs" in table

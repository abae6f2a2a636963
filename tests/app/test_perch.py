import json
from pathlib import Path

import pytest

from perchpose.app.perch import PerchOptions, run
from perchpose.errors import PerchposeError


def test_a_campaign_as_a_library_call(tmp_path: Path) -> None:
    """``run`` flies the runs asked for and writes the reports and the summary JSON; the
    JSON returned is the one written."""
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
    assert json.loads((tmp_path / "summary.json").read_text())["runs"] == 2
    rows = (out / "runs.csv").read_text().splitlines()
    assert len(rows) == 3  # header and two runs
    assert any("2 runs" in line for line in said)


def test_an_unknown_estimator_is_named(tmp_path: Path) -> None:
    with pytest.raises(PerchposeError, match=r"--estimator: unknown.*nope"):
        run(PerchOptions(str(tmp_path), estimators="truth,nope", runs=1))
    assert not (tmp_path / "runs.csv").exists()


def test_a_campaign_flown_on_full_state_setpoints_says_so(tmp_path: Path) -> None:
    """``command="full-state"``: the pilot sends positions the vehicle's position loop holds;
    a run perches in still air with the true pose, and the reports say which command flew."""
    out = tmp_path / "perch"
    said: list[str] = []
    options = PerchOptions(
        str(out), estimators="truth", runs=1, seed=3, workers=1, command="full-state"
    )
    content = run(options, say=said.append)
    assert content["command"] == "full-state"
    assert content["setup"]["command"] == "full-state"
    assert content["success_rate"] == 1.0
    assert any("full-state setpoints" in line for line in said)
    with pytest.raises(PerchposeError, match="--command: unknown 'attitude'"):
        run(PerchOptions(str(tmp_path / "other"), estimators="truth", runs=1, command="attitude"))

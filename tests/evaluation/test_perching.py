import json
from dataclasses import replace
from pathlib import Path

import pytest

from perchpose import CameraModel, TargetSpec
from perchpose.errors import CampaignError
from perchpose.evaluation.perching import (
    CampaignLog,
    RunRecord,
    markdown,
    read_runs,
    summary_json,
    wilson_interval,
)
from perchpose.sim.perch import PerchSetup


@pytest.fixture(scope="module")
def setup() -> PerchSetup:
    return PerchSetup(CameraModel.preset("fpv"), TargetSpec.paper(), estimator="truth")


def _record(seed: int, success: bool = True, wind: str = "light") -> RunRecord:
    return RunRecord(
        "truth",
        wind,
        1.5,
        0.5,
        seed,
        success,
        "perched" if success else "off-centre",
        3.0 + seed,
        0.2,
        5.0,
        0,
        90.0,
        "33",
    )


def test_wilson_interval() -> None:
    # textbook values: 8 of 10 -> (0.490, 0.943); 0 of 10 -> (0, 0.278); 1000 of 1000
    low, high = wilson_interval(8, 10)
    assert low == pytest.approx(0.4902, abs=1e-3)
    assert high == pytest.approx(0.9433, abs=1e-3)
    assert wilson_interval(0, 10) == pytest.approx((0.0, 0.2775), abs=1e-3)
    assert wilson_interval(1000, 1000)[0] == pytest.approx(0.99617, abs=1e-4)


def test_runs_are_written_one_by_one_and_resumed(tmp_path: Path, setup: PerchSetup) -> None:
    with CampaignLog(tmp_path, setup) as log:
        log.add(_record(0))
        # on disk before the campaign ends: a kill now loses nothing
        assert [r.seed for r in read_runs(log.path)] == [0]
        log.add(_record(1, success=False))
    # a run killed mid-row leaves a partial line; resume drops it and carries on
    with (tmp_path / "runs.csv").open("a") as f:
        f.write("truth,light,1.5,0.5,2,1,perch")
    with CampaignLog(tmp_path, setup, resume=True) as log:
        assert {k[-1] for k in log.done} == {0, 1}
        log.add(_record(2))
    assert [r.seed for r in read_runs(tmp_path / "runs.csv")] == [0, 1, 2]
    content = summary_json(list(read_runs(tmp_path / "runs.csv")), setup)
    assert content["runs"] == 3
    assert content["success_rate"] == pytest.approx(2 / 3)
    assert content["wind_mean_mps"] == 1.5
    assert content["turbulence_sigma_mps"] == 0.5
    json.dumps(content, default=str)


def test_the_hold_checks_that_dropped_and_the_refused_leans_are_read_back(
    tmp_path: Path, setup: PerchSetup
) -> None:
    with CampaignLog(tmp_path, setup) as log:
        log.add(replace(_record(0), seat_drops=2, leans_refused=True))
        log.add(_record(1))
    back = list(read_runs(tmp_path / "runs.csv"))
    assert [(r.seat_drops, r.leans_refused) for r in back] == [(2, True), (0, False)]
    content = summary_json(back, setup)
    cell = content["by_estimator"]["truth"]
    assert (cell["seat_drops"], cell["runs_with_seat_drops"], cell["leans_refused"]) == (2, 1, 1)


def test_resume_refuses_runs_of_another_setup(tmp_path: Path, setup: PerchSetup) -> None:
    with CampaignLog(tmp_path, setup) as log:
        log.add(_record(0))
    other = replace(setup, drop_probability=0.2)
    with pytest.raises(CampaignError, match="another setup"):
        CampaignLog(tmp_path, other, resume=True)
    # and nothing was lost
    assert [r.seed for r in read_runs(tmp_path / "runs.csv")] == [0]


def test_a_damaged_runs_file_is_named(tmp_path: Path) -> None:
    path = tmp_path / "runs.csv"
    path.write_text("estimator,wind\ntruth,light\ntruth,light\n")
    with pytest.raises(CampaignError, match=r"runs\.csv"):
        list(read_runs(path))


def test_markdown_has_a_row_per_wind_and_estimator() -> None:
    rows = [_record(k) for k in range(4)] + [_record(k, k % 2 == 0, "none") for k in range(4)]
    table = markdown(rows)
    assert "| light | 1.5 / 0.5 | truth | 33 | 4 | 100.0% |" in table
    assert "| none |" in table
    assert "off-centre 2" in table


def test_a_latency_sweep_has_a_cell_and_a_point_per_latency(tmp_path: Path) -> None:
    """Cells of several latencies are told apart (in the key, the names, the table) and drawn
    as success against latency."""
    rows = [replace(_record(k), latency_set_ms=lat) for lat in ("0", "100") for k in range(3)]
    rows[-1] = replace(rows[-1], success=False, reason="off-centre")
    setup = PerchSetup(CameraModel.preset("fpv"), TargetSpec.paper(), estimator="truth")
    content = summary_json(rows, setup)
    assert set(content["cells"]) == {"light/truth/0 ms", "light/truth/100 ms"}
    assert content["cells"]["light/truth/100 ms"]["success_rate"] == pytest.approx(2 / 3)
    assert len({r.key for r in rows}) == 6
    assert "| truth | 100 | 3 | 66.7% |" in markdown(rows)

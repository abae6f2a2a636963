import numpy as np
import pytest

from perchpose import CameraModel, TargetSpec
from perchpose.sim.campaign import SchedulerError, execute, run_campaign
from perchpose.sim.perch import PerchSetup


@pytest.fixture(scope="module")
def setup() -> PerchSetup:
    return PerchSetup(
        CameraModel.preset("fpv"), TargetSpec.paper(), estimator="truth", wind="light"
    )


def test_the_same_seeds_give_the_same_runs_on_a_dask_cluster(setup: PerchSetup) -> None:
    distributed = pytest.importorskip("dask.distributed")
    local = run_campaign(setup, runs=3, seed=20)
    with distributed.LocalCluster(
        n_workers=1, threads_per_worker=1, processes=True, dashboard_address=None
    ) as cluster:
        flown = run_campaign(setup, runs=3, seed=20, scheduler=cluster.scheduler_address)
    assert [r.seed for r in flown] == [20, 21, 22]
    for a, b in zip(local, flown, strict=True):
        assert a.reason == b.reason
        np.testing.assert_array_equal(a.p_magnet_m, b.p_magnet_m)


def test_a_scheduler_that_does_not_answer(setup: PerchSetup, silent_scheduler: str) -> None:
    with pytest.raises(SchedulerError, match="no Dask scheduler answered"):
        list(execute([(setup, 0)], scheduler=silent_scheduler))

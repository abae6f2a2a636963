import os
import subprocess
import sys
import time

import numpy as np
import pytest

from perchpose import CameraModel, TargetSpec
from perchpose.errors import SchedulerError
from perchpose.sim.campaign import execute, run_campaign
from perchpose.sim.perch import PerchSetup


@pytest.fixture(scope="module")
def setup() -> PerchSetup:
    return PerchSetup(
        CameraModel.preset("fpv"), TargetSpec.paper(), estimator="truth", wind="light"
    )


@pytest.mark.slow  # a local Dask cluster flies a campaign (about 9 s)
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


_POOL_SCRIPT = """
import sys, time
from perchpose.sim.campaign import worker_pool

pool = worker_pool(2)
for _ in range(2):
    pool.submit(time.sleep, 60)
time.sleep(0.5)
print("busy", flush=True)
time.sleep(60)
"""


def _descendants(pid: int) -> list[int]:
    """The processes started by ``pid``, and by those, and so on (Linux's /proc)."""
    parents: dict[int, int] = {}
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                with open(f"/proc/{entry}/stat", encoding="ascii") as f:
                    parents[int(entry)] = int(f.read().rsplit(")", 1)[1].split()[1])
            except (FileNotFoundError, ProcessLookupError):
                continue
    out, todo = [], [pid]
    while todo:
        current = todo.pop()
        children = [child for child, parent in parents.items() if parent == current]
        out += children
        todo += children
    return out


def _alive(pid: int) -> bool:
    """Whether process ``pid`` exists and is not a zombie (Linux's /proc)."""
    try:
        with open(f"/proc/{pid}/stat", encoding="ascii") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"
    except FileNotFoundError:
        return False


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_workers_end_when_their_parent_is_killed_outright() -> None:
    """A campaign killed with SIGKILL cannot cancel its jobs: its workers, busy or waiting,
    end on their own instead of waiting for work forever."""
    parent = subprocess.Popen(
        [sys.executable, "-c", _POOL_SCRIPT], stdout=subprocess.PIPE, text=True
    )
    try:
        assert parent.stdout is not None
        assert parent.stdout.readline().strip() == "busy"
        workers = _descendants(parent.pid)
        assert len(workers) >= 2
        assert all(_alive(pid) for pid in workers)
    finally:
        parent.kill()
        parent.wait()
    deadline = time.monotonic() + 10.0
    while any(_alive(pid) for pid in workers) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not any(_alive(pid) for pid in workers)

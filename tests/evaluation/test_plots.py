from pathlib import Path

import numpy as np
import pytest
from matplotlib.image import imread

from perchpose.evaluation.plots import bench_figure


def _times(n: int) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(3)
    base = rng.uniform(3.0, 5.0, n)
    return {"opencv": base, "fast": 0.25 * base * rng.uniform(0.8, 1.2, n), "slow": 2.0 * base}


def _stages(n: int) -> dict[str, np.ndarray]:
    return {stage: np.full(n, 0.1) for stage in ("detect", "corners", "pose", "filter", "fuse")}


def test_bench_figure_draws_each_methods_times_over_the_baseline(tmp_path: Path) -> None:
    n = 40
    ms = _times(n)
    out_of_view = np.zeros(n, dtype=bool)
    out_of_view[10:14] = True
    position = np.where(out_of_view, np.nan, 0.2)
    errors = {"fast": (position, position * 2), "slow": (position, position)}
    path = tmp_path / "bench.png"
    fig = bench_figure(str(path), ms, "opencv", _stages(n), out_of_view, errors)
    image = imread(path)
    assert image.shape[0] > 500
    assert image.shape[1] > 1000
    # four panels over the frames (times, stages, position, yaw) and the distribution beside
    assert len(fig.axes) == 5
    ratio_axes = fig.axes[-1]
    lines = {line.get_label(): line for line in ratio_axes.get_lines()}
    fast = next(line for label, line in lines.items() if label.startswith("fast"))
    x, share = fast.get_data()
    np.testing.assert_allclose(x, np.sort(ms["fast"] / ms["opencv"]))
    assert share[-1] == pytest.approx(1.0)
    median = np.median(ms["fast"] / ms["opencv"])
    assert fast.get_label() == f"fast (median {median:.2f}x)"
    assert not any(label.startswith("opencv (") for label in lines)
    # a method has one colour in every panel
    for name in ("fast", "slow"):
        colours = {
            line.get_color()
            for ax in fig.axes
            for line in ax.get_lines()
            if line.get_label().split(" ")[0] == name
        }
        assert len(colours) == 1


def test_bench_figure_without_truth_has_no_error_panels(tmp_path: Path) -> None:
    n = 12
    fig = bench_figure(
        str(tmp_path / "bench.svg"), _times(n), "opencv", _stages(n), np.zeros(n, bool), {}
    )
    assert len(fig.axes) == 3
    assert (tmp_path / "bench.svg").read_text().lstrip().startswith("<?xml")

"""Figures. Plot functions take matplotlib axes and data already computed."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure
from numpy.typing import NDArray

Array = NDArray[np.float64]

COMPONENTS = (("x", "cm"), ("y", "cm"), ("z", "cm"), ("yaw", "deg"))


def break_wraps_deg(values: Array, jump_deg: float = 180.0) -> Array:
    """A copy with NaN put where an angle series wraps, so a line plot does not draw the wrap
    as a vertical stroke across the axes."""
    out = np.asarray(values, dtype=np.float64).copy()
    jumps = np.flatnonzero(np.abs(np.diff(out)) > jump_deg)
    out[jumps + 1] = np.nan
    return out


def shade_mask(
    ax: Axes, t_s: Array, mask: NDArray[np.bool_], label: str, colour: str = "0.85"
) -> None:
    """Shade the time spans where ``mask`` is true."""
    labelled = False
    edges = np.flatnonzero(np.diff(np.concatenate([[0], mask.astype(int), [0]])))
    dt = float(np.median(np.diff(t_s))) if t_s.size > 1 else 0.0
    for start, stop in zip(edges[::2], edges[1::2], strict=True):
        ax.axvspan(
            t_s[start], t_s[stop - 1] + dt, color=colour, lw=0, label=None if labelled else label
        )
        labelled = True


def plot_kalman(
    axes: list[Axes],
    t_s: Array,
    raw: dict[str, Array],
    filtered: Array,
    truth: Array | None,
    dropout: NDArray[np.bool_],
) -> None:
    """The paper's Kalman figure: raw per-marker measurements (points) against the filtered,
    fused estimate (line) for x, y, z (cm) and yaw (deg), dropouts shaded.

    raw : marker label -> (N, 4) x_cm, y_cm, z_cm, yaw_deg with NaN where not measured.
    filtered, truth : (N, 4) in the same units.
    """
    markers = ("o", "s", "^", "v")
    for k, (ax, (name, unit)) in enumerate(zip(axes, COMPONENTS, strict=True)):
        shade_mask(ax, t_s, dropout, "dropout")
        if truth is not None:
            truth_k = break_wraps_deg(truth[:, k]) if name == "yaw" else truth[:, k]
            ax.plot(t_s, truth_k, color="black", lw=1.0, ls="--", label="truth")
        for j, (label, values) in enumerate(raw.items()):
            ax.plot(
                t_s,
                values[:, k],
                ls="none",
                marker=markers[j % 4],
                ms=2.5,
                alpha=0.6,
                label=f"raw {label}",
                color="tab:red" if j == 0 else "tab:orange",
            )
        filtered_k = break_wraps_deg(filtered[:, k]) if name == "yaw" else filtered[:, k]
        ax.plot(t_s, filtered_k, color="tab:blue", lw=1.4, label="filtered + fused")
        ax.set_ylabel(f"{name} ({unit})")
        ax.grid(True, lw=0.3)
    axes[-1].set_xlabel("time (s)")


def kalman_figure(
    path: str,
    t_s: Array,
    raw: dict[str, Array],
    filtered: Array,
    truth: Array | None,
    dropout: NDArray[np.bool_],
    title: str,
) -> None:
    """Write the Kalman figure as a PNG."""
    fig = Figure(figsize=(9, 9))
    axes = fig.subplots(4, 1, sharex=True)
    plot_kalman(list(axes), t_s, raw, filtered, truth, dropout)
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=len(labels), fontsize=8, frameon=False)
    fig.suptitle(title)
    fig.tight_layout(rect=(0.0, 0.03, 1.0, 1.0))
    fig.savefig(path, dpi=120)


def plot_ranges(
    ax: Axes,
    distances_cm: Array,
    probability: dict[str, Array],
    title: str,
    paper_cm: dict[str, float] | None = None,
) -> None:
    """Detection probability against distance (log axis) per marker."""
    styles = {
        "outer": ("tab:red", "outer marker"),
        "inner": ("tab:orange", "inner marker"),
        "fused": ("tab:blue", "estimate"),
    }
    for name, values in probability.items():
        colour, label = styles.get(name, ("0.3", name))
        ls = "--" if name == "fused" else "-"
        ax.plot(distances_cm, values, ls, marker="o", ms=3, color=colour, label=label)
    if paper_cm:
        for key, value in paper_cm.items():
            ax.axvline(value, color="0.6", lw=0.8, ls=":")
            ax.text(
                value,
                0.5,
                f"paper {key}",
                rotation=90,
                fontsize=7,
                ha="right",
                va="center",
                color="0.4",
                transform=ax.get_xaxis_transform(),
            )
    ax.set_xscale("log")
    ax.set_ylim(-0.03, 1.08)
    ax.set_xlabel("distance z (cm)")
    ax.set_ylabel("detection probability")
    ax.set_title(title, fontsize=10)
    ax.grid(True, which="both", lw=0.3)
    ax.legend(fontsize=7, loc="center left")


def ranges_figure(
    path: str, curves: list[tuple[str, Array, dict[str, Array]]], paper_cm: dict[str, float]
) -> None:
    """One panel per image quality."""
    fig = Figure(figsize=(4.2 * len(curves), 3.8))
    axes = fig.subplots(1, len(curves), squeeze=False)[0]
    for ax, (title, d, p) in zip(axes, curves, strict=True):
        plot_ranges(ax, d, p, title, paper_cm)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def plot_error_vs_distance(ax: Axes, series: dict[str, tuple[Array, Array]], unit: str) -> None:
    """Median error in distance bins for each variant: name -> (z_cm, error)."""
    all_z = np.concatenate([z for z, _ in series.values() if z.size]) if series else np.zeros(0)
    if all_z.size == 0:
        return
    edges = np.geomspace(max(1.0, float(np.nanmin(all_z))), float(np.nanmax(all_z)) * 1.001, 12)
    centres = np.sqrt(edges[:-1] * edges[1:])
    for name, (z, err) in series.items():
        med = np.full(len(centres), np.nan)
        for b in range(len(centres)):
            sel = (z >= edges[b]) & (z < edges[b + 1]) & np.isfinite(err)
            if np.count_nonzero(sel) >= 2:
                med[b] = np.median(err[sel])
        ax.plot(centres, med, marker="o", ms=3, label=name)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("distance z (cm)")
    ax.set_ylabel(f"median error ({unit})")
    ax.grid(True, which="both", lw=0.3)


def ablation_figure(
    path: str,
    position: dict[str, tuple[Array, Array]],
    yaw: dict[str, tuple[Array, Array]],
    title: str,
) -> None:
    """Position and yaw error against distance for each variant."""
    fig = Figure(figsize=(11, 4.2))
    ax_p, ax_y = fig.subplots(1, 2)
    plot_error_vs_distance(ax_p, position, "cm")
    ax_p.set_title("position error |estimate - truth|", fontsize=10)
    plot_error_vs_distance(ax_y, yaw, "deg")
    ax_y.set_title("yaw error", fontsize=10)
    ax_y.legend(fontsize=7)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def fusion_figure(
    path: str, names: list[str], least_squares: list[float], lms: list[float], paper: list[float]
) -> None:
    """Bar chart of the fitted sigmas against the paper's."""
    fig = Figure(figsize=(6, 3.5))
    ax = fig.subplots()
    x = np.arange(len(names))
    ax.bar(x - 0.27, least_squares, 0.27, label="least squares")
    ax.bar(x, lms, 0.27, label="LMS")
    ax.bar(x + 0.27, paper, 0.27, label="paper", color="0.6")
    ax.set_xticks(x, names)
    ax.set_ylabel("weight of the outer marker")
    ax.axhline(0, color="black", lw=0.5)
    ax.legend(fontsize=8)
    ax.grid(True, axis="y", lw=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def coverage_figure(
    path: str, corners_px: Array, size: tuple[int, int], grid: NDArray[np.int64], title: str
) -> None:
    """Heat map of corners per image cell, with every corner used."""
    w, h = size
    fig = Figure(figsize=(7, 7 * h / w + 0.8))
    ax = fig.subplots()
    shown = ax.imshow(grid, extent=(0, w, h, 0), cmap="viridis", interpolation="nearest")
    ax.plot(corners_px[:, 0], corners_px[:, 1], ".", color="white", ms=2, alpha=0.7)
    ax.set_xlim(0, w)
    ax.set_ylim(h, 0)
    ax.set_xlabel("u (px)")
    ax.set_ylabel("v (px)")
    ax.set_title(title, fontsize=10)
    fig.colorbar(shown, ax=ax, label="corners per cell", shrink=0.8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


STAGE_COLOURS = {1: "#fde0c5", 2: "#d4ecd4", 3: "#d6e4f5"}


def perch_figure(
    path: str,
    runs: list[tuple[str, Array, Array, NDArray[np.int64]]],
    plate_z_m: float,
    contact_radius_mm: float,
) -> None:
    """Height below the plate and lateral offset of the magnet against time for a few runs;
    the first run's detection stage shaded (1 outer, 2 both, 3 inner).

    runs : (label, t_s (N,), p_magnet_m (N, 3), stage (N,)).
    """
    fig = Figure(figsize=(10, 6.5))
    ax_z, ax_xy = fig.subplots(2, 1, sharex=True)
    if runs:
        _, t0, _, stage0 = runs[0]
        for stage, colour in STAGE_COLOURS.items():
            for ax in (ax_z, ax_xy):
                shade_mask(ax, t0, stage0 == stage, f"stage {stage} (first run)", colour)
    for label, t, p, _ in runs:
        ax_z.plot(t, (plate_z_m - p[:, 2]) * 100.0, lw=1.2, label=label)
        ax_xy.plot(t, np.maximum(np.hypot(p[:, 0], p[:, 1]) * 1000.0, 0.1), lw=1.2)
    ax_xy.axhline(contact_radius_mm, color="red", lw=0.8, ls="--", label="magnet radius")
    ax_z.set_ylabel("magnet below the plate (cm)")
    ax_xy.set_ylabel("lateral offset (mm)")
    ax_xy.set_yscale("log")
    ax_xy.set_ylim(bottom=0.1)
    ax_xy.set_xlabel("time (s)")
    for ax in (ax_z, ax_xy):
        ax.grid(True, lw=0.3)
    ax_z.legend(fontsize=7, ncol=3)
    ax_xy.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def sweep_figure(
    path: str,
    series: dict[str, list[tuple[float, int, int, dict[str, int]]]],
    interval: Callable[[int, int], tuple[float, float]],
    causes: tuple[str, ...],
    *,
    x_label: str = "mean wind (m/s)",
    unit: str = "m/s",
) -> None:
    """Success rate against what was swept (mean wind, camera latency) per estimator with
    each rate's interval (left), and the failures by cause per cell (right).

    series : estimator -> [(x, successes, runs, {cause: count})].
    """
    fig = Figure(figsize=(11, 4.5))
    ax_rate, ax_cause = fig.subplots(1, 2)
    for name, unsorted in series.items():
        points = sorted(unsorted)
        x = np.array([p[0] for p in points])
        rate = np.array([p[1] / p[2] for p in points]) * 100
        bounds = np.array([interval(p[1], p[2]) for p in points]) * 100
        ax_rate.errorbar(
            x,
            rate,
            yerr=[rate - bounds[:, 0], bounds[:, 1] - rate],
            marker="o",
            capsize=3,
            label=name,
        )
    ax_rate.set_xlabel(x_label)
    ax_rate.set_ylabel("perched (%), 95 % Wilson interval")
    ax_rate.set_ylim(-2, 102)
    ax_rate.grid(True, lw=0.3)
    ax_rate.legend(fontsize=8)
    labels: list[str] = []
    bottoms: list[float] = []
    rows = [(name, p) for name, points in series.items() for p in sorted(points)]
    for name, p in rows:
        labels.append(f"{name}\n{p[0]:g} {unit}")
        bottoms.append(0.0)
    for cause in causes:
        heights = [100.0 * p[3].get(cause, 0) / p[2] for _, p in rows]
        if any(heights):
            ax_cause.bar(range(len(rows)), heights, bottom=bottoms, label=cause)
            bottoms = [b + h for b, h in zip(bottoms, heights, strict=True)]
    ax_cause.set_xticks(range(len(rows)), labels, fontsize=7)
    ax_cause.set_ylabel("failed runs (%) by cause")
    if any(bottoms):
        ax_cause.legend(fontsize=8)
    else:
        ax_cause.text(0.5, 0.5, "no failures", ha="center", transform=ax_cause.transAxes)
    ax_cause.grid(True, axis="y", lw=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def bench_figure(
    path: str,
    ms: dict[str, Array],
    baseline: str,
    stages_ms: dict[str, Array],
    out_of_view: NDArray[np.bool_],
    errors: dict[str, tuple[Array, Array]],
) -> Figure:
    """What ``perchpose bench`` measured, frame by frame: each method's time (log scale) with
    the frames where no marker is in view shaded, the default pipeline's time by stage
    (stacked), with ``errors`` each pose method's position error (% of the distance) and yaw
    error (deg); beside them, each method's time over the baseline's on the same frame as a
    cumulative distribution. Returns the figure (also written to ``path``).

    ms : method -> (N,) ms per frame. stages_ms : stage -> (N,) ms per frame (the default
    pipeline's). errors : method -> ((N,) position %, (N,) yaw deg), NaN where unknown.
    """
    rows = 4 if errors else 2
    fig = Figure(figsize=(12, 2.4 * rows + 0.6))
    grid = fig.add_gridspec(rows, 2, width_ratios=(3, 1))
    frame = np.arange(len(out_of_view), dtype=np.float64)
    ax_ms = fig.add_subplot(grid[0, 0])
    left = [ax_ms] + [fig.add_subplot(grid[k, 0], sharex=ax_ms) for k in range(1, rows)]
    for ax in left:
        shade_mask(ax, frame, out_of_view, "no marker in view")
    others = [name for name in ms if name != baseline]
    colour = {name: f"C{k}" for k, name in enumerate(others)} | {baseline: "black"}
    for name, values in ms.items():
        ax_ms.plot(frame, values, lw=0.9, label=name, color=colour[name])
    ax_ms.set_yscale("log")
    ax_ms.set_ylabel("ms per frame")
    ax_stages = left[1]
    parts = [np.where(np.isfinite(v), v, 0.0) for v in stages_ms.values()]
    ax_stages.stackplot(frame, parts, labels=list(stages_ms), lw=0)
    ax_stages.set_ylabel("perchpose by stage (ms)")
    total = np.sum(parts, axis=0) if parts else np.zeros(0)
    if total.size and np.percentile(total, 99) > 0:  # a rare slow frame shows in the top panel
        ax_stages.set_ylim(0.0, 1.3 * float(np.percentile(total, 99)))
    if errors:
        panels = (
            (left[2], "position error (% of distance)", "1 %"),
            (left[3], "yaw error (deg)", "1 deg"),
        )
        for k, (ax_error, label, reference) in enumerate(panels):
            for name, series in errors.items():
                shown = np.maximum(series[k], 1e-4)
                ax_error.plot(frame, shown, ".", ms=3, label=name, color=colour[name])
            ax_error.axhline(1.0, color="red", lw=0.8, ls="--")
            ax_error.annotate(
                reference,
                (1.0, 1.0),
                xycoords=("axes fraction", "data"),
                ha="right",
                va="bottom",
                fontsize=7,
                color="red",
            )
            ax_error.set_yscale("log")
            ax_error.set_ylabel(label)
    left[-1].set_xlabel("frame")
    for ax in left:
        ax.grid(True, lw=0.3)
    for ax in left[:2]:  # the error panels draw each method in its colour in the first one
        ax.legend(fontsize=7, ncol=3, loc="upper right")
    ax_ratio = fig.add_subplot(grid[:, 1])
    base = ms[baseline]
    for name in others:
        ratio = np.sort(ms[name] / base)
        share = np.arange(1, ratio.size + 1) / ratio.size
        label = f"{name} (median {np.median(ratio):.2f}x)"
        ax_ratio.step(ratio, share, where="post", label=label, color=colour[name])
    ax_ratio.axvline(1.0, color="black", lw=0.8, label=baseline)
    ax_ratio.set_xscale("log")
    ax_ratio.set_xlabel(f"time over {baseline}'s, same frame")
    ax_ratio.set_ylabel("share of frames")
    ax_ratio.grid(True, lw=0.3)
    ax_ratio.legend(fontsize=7, loc="lower right")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    return fig

"""Figures. Plot functions take matplotlib axes and data already computed."""

from __future__ import annotations

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
    axes[0].legend(loc="upper right", fontsize=7, ncol=3)


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
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=120)

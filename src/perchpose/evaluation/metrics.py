"""Errors of a track file against a truth file, per frame and per stage."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from perchpose.errors import PerchposeError
from perchpose.geometry import wrap_angle_deg, yaw_rad
from perchpose.values import Estimate

Array = NDArray[np.float64]


@dataclass(frozen=True)
class FrameErrors:
    """Per-frame errors (estimate - truth) of the frames both files have.

    frame : (N,) int. stage : (N,) int, the estimate's stage. truth_stage : (N,) int.
    valid : (N,) bool, the estimate was valid. dropout : (N,) bool. predicted : (N,) bool, a
    valid estimate no measurement of its frame backs (the track file's ``predicted``).
    error_cm : (N, 3) x, y, z errors in cm (NaN where not valid). yaw_error_deg : (N,) wrapped.
    z_true_cm : (N,) true distance along the optical axis.
    """

    frame: NDArray[np.int64]
    t_s: Array
    stage: NDArray[np.int64]
    truth_stage: NDArray[np.int64]
    valid: NDArray[np.bool_]
    dropout: NDArray[np.bool_]
    error_cm: Array
    yaw_error_deg: Array
    z_true_cm: Array
    predicted: NDArray[np.bool_]


def normalised_error(estimate: Estimate, T_camera_target: Array) -> Array:
    """(4,) the estimate's x, y, z and yaw errors against the true pose ``T_camera_target``,
    each over the standard deviation the estimate reports for it (``Estimate.std``): over
    many frames, a covariance that matches the errors spreads these by 1."""
    true_yaw = yaw_rad(np.asarray(T_camera_target)[:3, :3])
    yaw_error = math.remainder(estimate.yaw_rad - true_yaw, 2 * math.pi)
    error = np.array([*(estimate.t_m - np.asarray(T_camera_target)[:3, 3]), yaw_error])
    out: Array = error / np.array(estimate.std)
    return out


def _f(row: dict[str, str], key: str) -> float:
    value = row.get(key, "")
    return float(value) if value not in ("", None) else math.nan


def frame_errors(track_rows: list[dict[str, str]], truth_rows: list[dict[str, str]]) -> FrameErrors:
    """Match rows by ``frame`` and compute the errors."""
    truth = {int(r["frame"]): r for r in truth_rows}
    matched = [(r, truth[int(r["frame"])]) for r in track_rows if int(r["frame"]) in truth]
    if not matched:
        raise PerchposeError("the track and truth files share no frame numbers")
    frame = np.array([int(r["frame"]) for r, _ in matched])
    valid = np.array([r["valid"] in ("1", "True", "true") for r, _ in matched])
    est = np.array([[_f(r, k) for k in ("x_cm", "y_cm", "z_cm", "yaw_deg")] for r, _ in matched])
    tru = np.array([[_f(t, k) for k in ("x_cm", "y_cm", "z_cm", "yaw_deg")] for _, t in matched])
    yaw_err = np.array(
        [
            wrap_angle_deg(a - b) if math.isfinite(a) and math.isfinite(b) else math.nan
            for a, b in zip(est[:, 3], tru[:, 3], strict=True)
        ]
    )
    return FrameErrors(
        frame=frame,
        t_s=np.array([_f(r, "t_s") for r, _ in matched]),
        stage=np.array([int(r.get("stage") or 0) for r, _ in matched]),
        truth_stage=np.array([int(t.get("stage") or 0) for _, t in matched]),
        valid=valid,
        dropout=np.array([t.get("dropout", "0") == "1" for _, t in matched]),
        error_cm=est[:, :3] - tru[:, :3],
        yaw_error_deg=yaw_err,
        z_true_cm=tru[:, 2],
        predicted=np.array([r.get("predicted", "") == "1" for r, _ in matched]),
    )


@dataclass(frozen=True)
class StageRow:
    """Error statistics of the valid frames of one stage (0 = all stages)."""

    stage: int
    frames: int
    median_abs_cm: tuple[float, float, float]
    p95_abs_cm: tuple[float, float, float]
    max_abs_cm: tuple[float, float, float]
    median_abs_yaw_deg: float
    max_abs_yaw_deg: float
    label: str = ""  # a group other than a stage ("measured", "predicted")


def _row(errors: FrameErrors, sel: NDArray[np.bool_], stage: int, label: str = "") -> StageRow:
    e = np.abs(errors.error_cm[sel])
    y = np.abs(errors.yaw_error_deg[sel])

    def trio(values: Array) -> tuple[float, float, float]:
        return (float(values[0]), float(values[1]), float(values[2]))

    return StageRow(
        stage=stage,
        frames=int(np.count_nonzero(sel)),
        median_abs_cm=trio(np.median(e, axis=0)),
        p95_abs_cm=trio(np.percentile(e, 95, axis=0)),
        max_abs_cm=trio(np.max(e, axis=0)),
        median_abs_yaw_deg=float(np.median(y)),
        max_abs_yaw_deg=float(np.max(y)),
        label=label,
    )


def stage_table(errors: FrameErrors) -> list[StageRow]:
    """One row per stage present among valid frames, then a row for all of them (stage 0)."""
    rows = []
    for stage in (1, 2, 3, 0):
        sel = errors.valid & ((errors.stage == stage) if stage else np.ones_like(errors.valid))
        if np.any(sel):
            rows.append(_row(errors, sel, stage))
    return rows


def measurement_table(errors: FrameErrors) -> list[StageRow]:
    """The valid frames in two rows: those measured in their own frame, and the filter's
    predictions (a dropout's coasted frames); a group without frames is left out."""
    groups = (("measured", errors.valid & ~errors.predicted), ("predicted", errors.predicted))
    return [_row(errors, sel, 0, label) for label, sel in groups if np.any(sel)]


def format_stage_table(rows: list[StageRow]) -> str:
    """A plain-text table of ``stage_table`` rows."""
    names = {0: "all", 1: "1 outer", 2: "2 both", 3: "3 inner"}
    header = (
        f"{'stage':<9} {'frames':>6}  {'median |err| x y z (cm)':>25}  "
        f"{'p95 |err| x y z (cm)':>22}  {'yaw med/max (deg)':>17}"
    )
    lines = [header, "-" * len(header)]
    for r in rows:
        med = " ".join(f"{v:6.2f}" for v in r.median_abs_cm)
        p95 = " ".join(f"{v:6.2f}" for v in r.p95_abs_cm)
        lines.append(
            f"{r.label or names[r.stage]:<9} {r.frames:>6}  {med:>25}  {p95:>22}  "
            f"{r.median_abs_yaw_deg:7.2f}/{r.max_abs_yaw_deg:<7.2f}"
        )
    return "\n".join(lines)

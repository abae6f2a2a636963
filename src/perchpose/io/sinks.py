"""Pose sinks: CSV and JSON Lines, one row per input frame, in input order."""

from __future__ import annotations

import csv
import io
import json
import math
import os
from pathlib import Path
from typing import IO, Any, Protocol

import numpy as np
from numpy.typing import NDArray

from perchpose.control.time_offset import TimeOffset
from perchpose.errors import PerchposeError
from perchpose.io.frames import Stamp
from perchpose.target import TargetSpec
from perchpose.values import POSE_COLUMNS, Estimate


class TrackWriter(Protocol):
    """Where a track's frames go: a pose file (``PoseWriter``) or a ROS 2 bag
    (``perchpose.io.ros.bag_writer.BagWriter``), which also takes each frame's overlay
    (``wants_overlay``)."""

    rows: int
    wants_overlay: bool

    def write_frame(
        self,
        row: dict[str, Any],
        estimate: Estimate | None,
        stamp: Stamp,
        overlay: NDArray[np.uint8] | None = None,
    ) -> None: ...

    def close(self) -> None: ...


def raw_columns(target: TargetSpec) -> tuple[str, ...]:
    """Per-marker raw measurement columns: ``m{i}_x_cm`` ... ``m{i}_yaw_deg``, i = marker index
    (0 is the largest marker)."""
    return tuple(
        f"m{i}_{field}"
        for i in range(len(target.markers))
        for field in ("x_cm", "y_cm", "z_cm", "yaw_deg", "reproj_px")
    )


# the pose's tilt and the standard deviations its covariance gives
UNCERTAINTY_COLUMNS = ("roll_deg", "pitch_deg", "x_std_cm", "y_std_cm", "z_std_cm", "yaw_std_deg")


# the flying controller's estimate of the camera-to-vehicle time offset (control.time_offset)
OFFSET_COLUMNS = ("time_offset_ms", "time_offset_sigma_ms")


def columns(target: TargetSpec) -> tuple[str, ...]:
    """All columns of a track file."""
    return (
        *POSE_COLUMNS,
        *UNCERTAINTY_COLUMNS,
        *raw_columns(target),
        "total_ms",
        "latency_ms",
        "age_s",
        "measured",
        "predicted",
        "skipped",
        *OFFSET_COLUMNS,
        "error",
        "file",
    )


def offset_columns(estimate: TimeOffset | None) -> dict[str, str]:
    """A row's time-offset columns: the estimate and its spread, ms (empty: none yet)."""
    if estimate is None:
        return dict.fromkeys(OFFSET_COLUMNS, "")
    return {
        "time_offset_ms": _num(estimate.offset_s * 1000.0, 2),
        "time_offset_sigma_ms": _num(estimate.sigma_s * 1000.0, 2),
    }


def _num(value: float, digits: int) -> str:
    return "" if not math.isfinite(value) else f"{value:.{digits}f}"


def estimate_row(
    frame: int,
    t_s: float,
    estimate: Estimate | None,
    target: TargetSpec,
    error: str = "",
    file: str = "",
) -> dict[str, Any]:
    """The row of one frame; ``estimate`` None for a frame that could not be processed.
    ``age_s`` is 0 for a pose measured in this frame and the age of the newest measurement
    for a filter's prediction; ``measured`` the markers measured in this frame (``m0+m1``: the
    indices of the ``m{i}_*`` columns); ``predicted`` 1 for a valid pose that no measurement
    of this frame backs (the filter coasting), 0 for a measured one; ``latency_ms`` the time
    from the frame's capture (a file's reading) to its estimate, where known; ``skipped`` what
    the detection left out to keep to its time budget (``;``-separated); ``file`` names the
    frame's source."""
    row: dict[str, Any] = dict.fromkeys(columns(target), "")
    row.update(frame=frame, t_s=f"{t_s:.6f}", valid=0, stage=0, error=error, file=file)
    if estimate is None:
        return row
    row.update(
        valid=int(estimate.valid),
        stage=estimate.stage,
        total_ms=f"{estimate.timings.total_ms:.2f}",
        latency_ms=_num(estimate.latency_s * 1e3, 2),
        measured=estimate.measured_label,
        skipped=";".join(estimate.skipped),
    )
    if estimate.valid:
        row.update(
            predicted=int(estimate.predicted),
            age_s=_num(estimate.age_s, 4),
            x_cm=_num(estimate.x_cm, 4),
            y_cm=_num(estimate.y_cm, 4),
            z_cm=_num(estimate.z_cm, 4),
            yaw_deg=_num(estimate.yaw_deg, 3),
            roll_deg=_num(math.degrees(estimate.roll_rad), 3),
            pitch_deg=_num(math.degrees(estimate.pitch_rad), 3),
        )
        x_std, y_std, z_std, yaw_std = estimate.std
        row.update(
            x_std_cm=_num(x_std * 100.0, 6),
            y_std_cm=_num(y_std * 100.0, 6),
            z_std_cm=_num(z_std * 100.0, 6),
            yaw_std_deg=_num(math.degrees(yaw_std), 5),
        )
    for i, m in enumerate(estimate.markers):
        if m.measurement is None:
            continue
        t = m.measurement.t_m * 100.0
        row[f"m{i}_x_cm"] = _num(float(t[0]), 4)
        row[f"m{i}_y_cm"] = _num(float(t[1]), 4)
        row[f"m{i}_z_cm"] = _num(float(t[2]), 4)
        row[f"m{i}_yaw_deg"] = _num(math.degrees(m.measurement.yaw_rad), 3)
        row[f"m{i}_reproj_px"] = _num(m.measurement.reproj_rms_px, 3)
    return row


class PoseWriter:
    """Writes rows to ``path``: CSV (``.csv``) or JSON Lines (``.jsonl``).

    Each row reaches the file whole as it is written (flushed row by row: a run killed at any
    point keeps every finished row); a write that fails (a full disk) cuts the file back to its
    last whole row and raises ``PerchposeError`` naming the file.
    """

    def __init__(self, path: str | Path, target: TargetSpec) -> None:
        self.path = Path(path)
        suffix = self.path.suffix.lower()
        if suffix not in (".csv", ".jsonl"):
            raise PerchposeError(
                f"{self.path}: output must end in .csv, .jsonl or .mcap (or name a bag folder)"
            )
        self.target = target
        self._jsonl = suffix == ".jsonl"
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._file: IO[str] = self.path.open("w", newline="", encoding="utf-8")
        except OSError as exc:
            raise PerchposeError(f"{self.path}: cannot write ({exc.strerror})") from exc
        self._buffer = io.StringIO()
        self._csv = None
        self.rows = 0
        self._good_bytes = 0
        if not self._jsonl:
            self._csv = csv.DictWriter(self._buffer, fieldnames=list(columns(target)))
            self._csv.writeheader()
            self._commit()

    def _commit(self) -> None:
        text = self._buffer.getvalue()
        self._buffer.seek(0)
        self._buffer.truncate()
        try:
            self._file.write(text)
            self._file.flush()
        except OSError as exc:
            self._cut_back()
            raise PerchposeError(
                f"{self.path}: cannot write ({exc.strerror}); {self.rows} whole rows kept"
            ) from exc
        self._good_bytes = self._file.tell()

    def _cut_back(self) -> None:
        """Drop a partly written row (best effort: the disk may refuse even this)."""
        try:
            os.truncate(self.path, self._good_bytes)
        except OSError:
            return

    def write(self, row: dict[str, Any]) -> None:
        """Append one row."""
        if self._csv is not None:
            self._csv.writerow(row)
        else:
            self._buffer.write(json.dumps(track_json(row)) + "\n")
        self._commit()
        self.rows += 1

    wants_overlay = False

    def write_frame(
        self,
        row: dict[str, Any],
        estimate: Estimate | None,
        stamp: Stamp,
        overlay: NDArray[np.uint8] | None = None,
    ) -> None:
        """Append one frame's row (what else a frame brings goes into bags only)."""
        self.write(row)

    def close(self) -> None:
        """Close the file (every written row is already in it)."""
        try:
            self._file.close()
        except OSError as exc:
            self._cut_back()
            raise PerchposeError(f"{self.path}: cannot write ({exc.strerror})") from exc

    def __enter__(self) -> PoseWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def track_json(row: dict[str, Any]) -> dict[str, Any]:
    """A track row as JSON takes it: numbers as numbers, an empty cell as null."""
    return {key: _json_value(value) for key, value in row.items()}


def _json_value(value: Any) -> Any:
    if value == "":
        return None
    if isinstance(value, str):
        for kind in (int, float):
            try:
                return kind(value)
            except ValueError:
                pass
    return value


def read_track_csv(path: str | Path) -> list[dict[str, str]]:
    """Read a track or truth CSV as a list of rows (strings, empty for missing values)."""
    p = Path(path)
    try:
        with p.open(newline="", encoding="utf-8") as f:
            return list(csv.DictReader(f))
    except OSError as exc:
        raise PerchposeError(f"{p}: cannot read ({exc.strerror})") from exc

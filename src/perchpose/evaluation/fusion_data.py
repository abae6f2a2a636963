"""Labelled data for fitting the fusion sigmas: truth beside both markers' raw measurements."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import numpy as np

from perchpose.errors import PerchposeError
from perchpose.evaluation.experiments import FusionFit, FusionSamples
from perchpose.io.sinks import read_track_csv

COMPONENTS = ("x_cm", "y_cm", "z_cm", "yaw_deg")
TRUTH_COLUMNS = tuple(f"true_{c}" for c in COMPONENTS)
OUTER_COLUMNS = tuple(f"m0_{c}" for c in COMPONENTS)
INNER_COLUMNS = tuple(f"m1_{c}" for c in COMPONENTS)


def write_fusion_csv(path: str | Path, samples: FusionSamples) -> None:
    """Write ``position, true_*, m0_*, m1_*`` rows (cm and deg)."""
    with Path(path).open("w", newline="", encoding="utf-8") as f:
        w = csv.writer(f)
        w.writerow(["position", *TRUTH_COLUMNS, *OUTER_COLUMNS, *INNER_COLUMNS])
        for k in range(samples.truth.shape[0]):
            index = int(samples.position_index[k]) if samples.position_index.size else 0
            w.writerow(
                [
                    index,
                    *(f"{v:.5f}" for v in samples.truth[k]),
                    *(f"{v:.5f}" for v in samples.outer[k]),
                    *(f"{v:.5f}" for v in samples.inner[k]),
                ]
            )


def _number(row: dict[str, str], key: str, where: str) -> float:
    raw = row.get(key)
    if raw is None:
        raise PerchposeError(f"{where}: missing column {key!r}")
    if raw == "":
        return math.nan
    try:
        return float(raw)
    except ValueError as exc:
        raise PerchposeError(f"{where}: column {key!r} has {raw!r}, not a number") from exc


def load_fusion_samples(path: str | Path, truth_path: str | Path | None = None) -> FusionSamples:
    """Read labelled data: a CSV with ``true_*`` and ``m0_*``/``m1_*`` columns, or a track CSV
    (``perchpose track``) with the ``truth.csv`` of the same frames. Rows where either marker
    has no measurement are skipped."""
    p = Path(path)
    if not p.is_file():
        raise PerchposeError(f"{p}: file not found")
    rows = read_track_csv(p)
    if not rows:
        raise PerchposeError(f"{p}: no rows")
    if truth_path is not None:
        tp = Path(truth_path)
        if not tp.is_file():
            raise PerchposeError(f"{tp}: file not found")
        truth_by_frame = {r.get("frame", ""): r for r in read_track_csv(tp)}
        joined = []
        for r in rows:
            t = truth_by_frame.get(r.get("frame", ""))
            if t is not None:
                joined.append({**r, **{f"true_{c}": t.get(c, "") for c in COMPONENTS}})
        rows = joined
        if not rows:
            raise PerchposeError(f"{p} and {tp} share no frame numbers")
    if truth_path is None and TRUTH_COLUMNS[0] not in rows[0] and "frame" in rows[0]:
        raise PerchposeError(
            f"{p}: a track file has no truth columns: give the truth.csv of the same frames "
            "with --truth"
        )
    truth, outer, inner = [], [], []
    for n, r in enumerate(rows, start=2):
        where = f"{p}, line {n}"
        true_values = [_number(r, c, where) for c in TRUTH_COLUMNS]
        outer_values = [_number(r, c, where) for c in OUTER_COLUMNS]
        inner_values = [_number(r, c, where) for c in INNER_COLUMNS]
        if all(math.isfinite(v) for v in (*true_values, *outer_values, *inner_values)):
            truth.append(true_values)
            outer.append(outer_values)
            inner.append(inner_values)
    if len(truth) < 2:
        raise PerchposeError(f"{p}: fewer than 2 rows with truth and both markers measured")
    return FusionSamples(np.array(truth), np.array(outer), np.array(inner))


def write_fusion_fit(path: str | Path, fit: FusionFit) -> None:
    """The fit as JSON: the least-squares weights under ``FusionSigmas``' field names at the
    top level (``FusionSigmas.load`` and ``perchpose track --sigmas`` read them), and beside
    them both fits under the paper's names and the number of frames."""
    content = {
        **fit.sigmas().to_dict(),
        "method": "least_squares",
        "least_squares": fit.least_squares,
        "lms": fit.lms,
        "samples": fit.samples,
    }
    try:
        Path(path).write_text(json.dumps(content, indent=2), encoding="utf-8")
    except OSError as exc:
        raise PerchposeError(f"{path}: cannot write ({exc.strerror})") from exc

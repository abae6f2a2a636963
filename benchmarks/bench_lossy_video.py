"""Frames a lost packet spoils: what measuring them costs, and what flagging them saves.

    .venv/bin/python benchmarks/bench_lossy_video.py [--camera webcam] [--gop 30]
        [--drop 40 130] [--cut 75 170] [--seed 3] [--out FOLDER]

Renders an 8 s approach from 2 m (``perchpose.sim.scenarios.approach``, default images, no
dropouts) through ``--camera``, encodes it as H.264 (libx264, a key frame every ``--gop``
frames, no B-frames, CRF 18) and loses the packets of the frames in ``--drop`` and the second
halves of those in ``--cut`` (``perchpose.sim.lossy_video``). Then tracks three ways, each with
a fresh ``PerchingEstimator``: the clean video; the lossy one with every decoded frame measured
(as if the damage were not known); the lossy one as ``perchpose track`` reads it (frames that
rest on damaged data not measured). Prints, for each, the valid frames and the position error
(|estimate - truth|, cm) over the frames the damage spoils and over the others.
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import cv2
import numpy as np

from perchpose import CameraModel, PerchingEstimator, TargetSpec
from perchpose.evaluation.metrics import frame_errors
from perchpose.io.sinks import estimate_row, read_track_csv
from perchpose.io.sources import open_source
from perchpose.sim.lossy_video import encode_h264, lose_packets
from perchpose.sim.scenarios import approach
from perchpose.sim.sequence import write_sequence


def track_rows(video: Path, camera: CameraModel, measure_damaged: bool) -> list[dict[str, str]]:
    """One row per frame of ``video``, as strings (as read back from a track file)."""
    target = TargetSpec.paper()
    estimator = PerchingEstimator(camera, target)
    rows = []
    for frame in open_source(str(video)):
        estimate = None
        if frame.image is not None and (measure_damaged or not frame.damaged):
            estimate = estimator.update(camera.check_image(frame.image), frame.t_s)
        row = estimate_row(frame.index, frame.t_s, estimate, target, frame.error)
        rows.append({k: str(v) for k, v in row.items()})
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--camera", default="webcam", help="a preset: webcam, fpv, fpv_wide")
    parser.add_argument("--gop", type=int, default=30)
    parser.add_argument("--drop", type=int, nargs="*", default=[40, 130])
    parser.add_argument("--cut", type=int, nargs="*", default=[75, 170])
    parser.add_argument("--seed", type=int, default=3)
    parser.add_argument("--out", type=Path, default=None, help="keep the files here")
    args = parser.parse_args()
    out = args.out or Path(tempfile.mkdtemp(prefix="perchpose-lossy-"))
    camera = CameraModel.preset(args.camera)
    sequence = write_sequence(
        approach(duration_s=8.0, start_z_m=2.0, dropouts=()),
        camera,
        TargetSpec.paper(),
        out / "sequence",
        seed=args.seed,
        progress=False,
    )
    images = (cv2.imread(str(p)) for p in sorted(sequence.glob("frame_*.png")))
    clean = encode_h264(images, out / "clean.mp4", args.gop)
    lossy = lose_packets(clean, out / "lossy.mp4", set(args.drop), set(args.cut))
    truth = read_track_csv(sequence / "truth.csv")
    runs = {
        "clean": track_rows(clean, camera, measure_damaged=True),
        "lossy, every frame measured": track_rows(lossy, camera, measure_damaged=True),
        "lossy, damaged frames flagged": track_rows(lossy, camera, measure_damaged=False),
    }
    flagged = runs["lossy, damaged frames flagged"]
    spoiled = {int(r["frame"]) for r in flagged if r["error"].endswith("not measured")}
    print(
        f"{args.camera}, GOP {args.gop}, frames dropped {args.drop}, cut {args.cut}: "
        f"{len(spoiled)} frames rest on damaged data; files in {out}"
    )
    print(f"{'run':32s} {'valid':>5s}  {'spoiled: mean max':>18s}  {'others: mean p95 max':>22s}")
    for name, rows in runs.items():
        errors = frame_errors(rows, truth)
        norm = np.linalg.norm(errors.error_cm, axis=1)
        seen = errors.valid & (errors.truth_stage > 0)
        on_spoiled = seen & np.isin(errors.frame, sorted(spoiled))
        others = seen & ~np.isin(errors.frame, sorted(spoiled))
        spoiled_text = (
            f"{norm[on_spoiled].mean():8.2f} {norm[on_spoiled].max():5.2f}"
            if on_spoiled.any()
            else f"{'-':>8s} {'-':>5s}"
        )
        print(
            f"{name:32s} {int(errors.valid.sum()):5d}  {spoiled_text:>18s}  "
            f"{norm[others].mean():8.3f} {np.percentile(norm[others], 95):6.3f} "
            f"{norm[others].max():6.2f}"
        )


if __name__ == "__main__":
    main()

"""Detection cost: the target's own dictionaries against OpenCV's full predefined ones.

    .venv/bin/python benchmarks/bench_detection.py [--camera webcam] [--frames 40]

Renders an approach from 1.5 m to 0.12 m and times one ``detectMarkersMultiDict`` call per
frame with both kinds of dictionaries, on the same frames in the same run, single-threaded.
Prints the ratio (full / target-only) and the frames where the two find different target
markers (with a full dictionary, a noisy read of a marker as another id can shadow the right
reading of the same quad, so the target-only search can only find more).
"""

from __future__ import annotations

import argparse
import time

import cv2
import numpy as np

from perchpose import CameraModel, TargetSpec
from perchpose.detection.quads import detector_parameters, target_dictionaries
from perchpose.geometry import facing_pose
from perchpose.sim.render import ImageQuality, Renderer
from perchpose.target import aruco_dictionary


def detector(dictionaries: list[cv2.aruco.Dictionary]) -> cv2.aruco.ArucoDetector:
    d = cv2.aruco.ArucoDetector(dictionaries[0], detector_parameters())
    d.setDictionaries(dictionaries)
    return d


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--camera", default="webcam")
    parser.add_argument("--frames", type=int, default=40)
    args = parser.parse_args()
    cv2.setNumThreads(1)
    camera = CameraModel.preset(args.camera)
    target = TargetSpec.paper()
    renderer = Renderer(camera, target, supersample=1)
    rng = np.random.default_rng(0)
    frames = [
        renderer.render(facing_pose(0.1 * z * np.sin(k), 0.05 * z, z, 0.3 * k), ImageQuality(), rng)
        for k, z in enumerate(np.geomspace(1.5, 0.12, args.frames))
    ]
    subset, members = target_dictionaries(target)
    full = [aruco_dictionary(n) for n in target.dictionaries]
    candidates = {"target-only": detector(subset), "full": detector(full)}
    spent = dict.fromkeys(candidates, 0.0)
    found = {name: [] for name in candidates}
    for _ in range(3):
        for image in frames:
            for name, det in candidates.items():
                t0 = time.process_time()
                _, ids, _, which = det.detectMarkersMultiDict(image)
                spent[name] += time.process_time() - t0
                if ids is None:
                    found[name].append(set())
                    continue
                pairs = zip(ids.reshape(-1), which.reshape(-1), strict=True)
                if name == "full":
                    marks = {(target.dictionaries[int(d)], int(i)) for i, d in pairs}
                    found[name].append(
                        {
                            k
                            for k, m in enumerate(target.markers)
                            if (m.dictionary, m.marker_id) in marks
                        }
                    )
                else:
                    found[name].append({members[int(d)][int(i)] for i, d in pairs})
    n = 3 * len(frames)
    for name, total in spent.items():
        print(f"{name:12s} {1e3 * total / n:6.2f} ms per frame")
    print(f"ratio full / target-only: {spent['full'] / spent['target-only']:.1f}x")
    pairs = list(zip(found["target-only"], found["full"], strict=True))
    same = sum(a == b for a, b in pairs)
    print(f"same target markers found on {same} of {n} frames")
    for k, (a, b) in enumerate(pairs):
        if a != b:
            print(f"  frame {k % len(frames)}: target-only {sorted(a)}, full {sorted(b)}")


if __name__ == "__main__":
    main()

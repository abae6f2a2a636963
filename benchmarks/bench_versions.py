"""Two versions of perchpose on the same frames, taking turns frame by frame.

    .venv/bin/python benchmarks/bench_versions.py --base REV [--new REV] [--camera fpv]
        [--quality default] [--frames 240] [--seed 0] [--repeat 3] [--cold] [--json FILE]

A change to the pipeline's speed is smaller than what a busy machine does to two runs timed
one after the other (``perchpose bench``'s ratios move by up to 0.1 between runs of the same
code). Here each version runs in its own process, both pinned to one core, and they take
turns on every frame (the order alternating frame by frame and run by run), so both see the
same machine. ``--base`` is a git revision; ``--new`` another one, or the working tree
(default). A revision's ``src/perchpose`` is exported once to a folder in the system's
temporary directory named by its commit, where numba keeps its compiled cache: the first run
of a revision compiles it (a minute or more).

The frames are the rendered approach of ``perchpose bench`` (rendered by the working tree);
each frame's time is ``PerchingEstimator.update`` alone, wall-clock inside the worker (the
least of ``--repeat`` runs), with a fresh estimator for each run (``--cold``: for every
frame). Reported: each version's median, p95, p99 and largest time, the new over the base at
each, and how far the two versions' estimates are apart (frames where one has a pose and the
other not, the largest position and yaw differences, and the largest difference of the
covariances relative to their size).
"""

from __future__ import annotations

import argparse
import io
import json
import os
import subprocess
import sys
import tarfile
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO

import numpy as np

REPO = Path(__file__).resolve().parent.parent
WORKTREE = "worktree"


class VersionError(Exception):
    """A revision that cannot be exported."""


def commit_of(rev: str) -> str:
    """The full commit hash of ``rev`` in this repository."""
    done = subprocess.run(
        ["git", "-C", str(REPO), "rev-parse", "--verify", f"{rev}^{{commit}}"],
        capture_output=True,
        text=True,
        check=False,
    )
    if done.returncode != 0:
        raise VersionError(f"--base/--new: {rev!r} is not a commit of {REPO}")
    return done.stdout.strip()


def exported_src(rev: str) -> Path:
    """A folder holding ``src/perchpose`` as it is at ``rev`` (``WORKTREE``: this checkout's
    own ``src``), exported once per commit."""
    if rev == WORKTREE:
        return REPO / "src"
    commit = commit_of(rev)
    folder = Path(tempfile.gettempdir()) / f"perchpose-rev-{commit[:12]}"
    if not (folder / "perchpose" / "__init__.py").exists():
        archive = subprocess.run(
            ["git", "-C", str(REPO), "archive", commit, "src/perchpose"],
            capture_output=True,
            check=True,
        ).stdout
        with tarfile.open(fileobj=io.BytesIO(archive)) as tar:
            members = [m for m in tar.getmembers() if m.name.startswith("src/perchpose")]
            for member in members:
                member.name = member.name[len("src/") :]
            tar.extractall(folder, members=members, filter="data")
    return folder


@dataclass
class Worker:
    """One version's process: it loads the frames and answers one frame a request."""

    name: str
    process: subprocess.Popen[str]
    ms: list[list[float]] = field(default_factory=list)
    estimates: list[dict[str, object]] = field(default_factory=list)

    def ask(self, request: str) -> dict[str, object]:
        stdin, stdout = self.process.stdin, self.process.stdout
        assert stdin is not None
        assert stdout is not None
        stdin.write(request + "\n")
        stdin.flush()
        line = stdout.readline()
        if not line:
            raise VersionError(f"the {self.name} version's worker ended (its stderr is above)")
        answer: dict[str, object] = json.loads(line)
        return answer


def start_worker(name: str, src: Path, frames_path: Path, camera: str, cpu: int | None) -> Worker:
    env = dict(os.environ, PYTHONPATH=str(src))
    command = [sys.executable, str(Path(__file__).resolve()), "--worker", str(frames_path)]
    process = subprocess.Popen(
        [*command, "--camera", camera],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
        env=env,
    )
    if cpu is not None:
        os.sched_setaffinity(process.pid, {cpu})
    worker = Worker(name, process)
    worker.ask("ready")  # imported, compiled and warmed up
    return worker


def serve(frames_path: Path, camera_name: str, stdin: IO[str], stdout: IO[str]) -> None:
    """The worker: requests ``ready``, ``fresh`` (a new estimator) and a frame index (its
    update, timed), each answered by one JSON line."""
    import cv2

    from perchpose import CameraModel, PerchingEstimator, TargetSpec

    cv2.setNumThreads(1)
    stored = np.load(frames_path)
    images, t_s = list(stored["images"]), [float(t) for t in stored["t_s"]]
    camera, target = CameraModel.preset(camera_name), TargetSpec.paper()
    warm = PerchingEstimator(camera, target)
    for image, t in zip(images[:30], t_s[:30], strict=False):
        warm.update(image, t)
    estimator = PerchingEstimator(camera, target)
    for line in stdin:
        request = line.strip()
        answer: dict[str, object] = {}
        if request == "fresh":
            estimator = PerchingEstimator(camera, target)
        elif request != "ready":
            i = int(request)
            t0 = time.perf_counter()
            estimate = estimator.update(images[i], t_s[i])
            answer["ms"] = (time.perf_counter() - t0) * 1e3
            answer["valid"] = bool(estimate.valid)
            answer["t_m"] = [float(v) for v in estimate.t_m]
            answer["yaw_rad"] = float(estimate.yaw_rad)
            cov = estimate.covariance
            answer["covariance"] = None if cov is None else np.asarray(cov).ravel().tolist()
        stdout.write(json.dumps(answer) + "\n")
        stdout.flush()


def percentiles(ms: np.ndarray) -> dict[str, float]:
    return {
        "p50": float(np.median(ms)),
        "p95": float(np.percentile(ms, 95)),
        "p99": float(np.percentile(ms, 99)),
        "max": float(ms.max()),
    }


def apart(base: list[dict[str, object]], new: list[dict[str, object]]) -> dict[str, float]:
    """How far two versions' estimates of the same frames are apart."""
    differ = 0
    position_m = yaw_rad = covariance = 0.0
    for a, b in zip(base, new, strict=True):
        if a["valid"] != b["valid"]:
            differ += 1
            continue
        if not a["valid"]:
            continue
        pa, pb = np.asarray(a["t_m"]), np.asarray(b["t_m"])
        position_m = max(position_m, float(np.abs(pa - pb).max()))
        yaw_rad = max(yaw_rad, abs(float(a["yaw_rad"]) - float(b["yaw_rad"])))  # type: ignore[arg-type]
        ca, cb = a["covariance"], b["covariance"]
        if (ca is None) != (cb is None):
            covariance = float("inf")
        elif ca is not None:
            ca_, cb_ = np.asarray(ca), np.asarray(cb)
            covariance = max(covariance, float(np.abs(ca_ - cb_).max() / np.abs(ca_).max()))
    return {
        "frames_valid_differs": differ,
        "position_m": position_m,
        "yaw_rad": yaw_rad,
        "covariance_relative": covariance,
    }


def main() -> None:
    if sys.argv[1:2] == ["--worker"]:
        worker = argparse.ArgumentParser()
        worker.add_argument("--worker", type=Path, required=True)
        worker.add_argument("--camera", required=True)
        own = worker.parse_args()
        serve(own.worker, own.camera, sys.stdin, sys.stdout)
        return
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--base", required=True, help="git revision to compare against")
    parser.add_argument("--new", default=WORKTREE, help="git revision (default: the working tree)")
    parser.add_argument("--camera", default="fpv", choices=["fpv", "fpv_wide", "webcam"])
    parser.add_argument(
        "--quality", default="default", choices=["default", "clean", "analog_fpv", "harsh"]
    )
    parser.add_argument("--frames", type=int, default=240)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--cold", action="store_true", help="a fresh estimator for every frame")
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    try:
        run(args)
    except VersionError as error:
        print(f"bench_versions: {error}", file=sys.stderr)
        sys.exit(2)


def run(args: argparse.Namespace) -> None:
    from tqdm import tqdm

    from perchpose import CameraModel, TargetSpec
    from perchpose.app.bench import rendered_frames
    from perchpose.sim.render import ImageQuality

    sources = {"base": exported_src(args.base), "new": exported_src(args.new)}
    camera = CameraModel.preset(args.camera)
    quality = ImageQuality.preset(args.quality)
    frames = rendered_frames(camera, TargetSpec.paper(), args.frames, quality, args.seed, True)
    n = len(frames.images)
    cpu = min(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None
    with tempfile.TemporaryDirectory() as folder:
        frames_path = Path(folder) / "frames.npz"
        np.savez(frames_path, images=np.stack(frames.images), t_s=np.asarray(frames.t_s))
        print("starting both versions (a revision's first run compiles it)", file=sys.stderr)
        workers = [
            start_worker(k, src, frames_path, args.camera, cpu) for k, src in sources.items()
        ]
        try:
            for worker in workers:
                worker.ms = [[np.inf] * n for _ in range(args.repeat)]
            with tqdm(total=args.repeat * n, desc="frames", unit="frame") as bar:
                for r in range(args.repeat):
                    for worker in workers:
                        worker.ask("fresh")
                        worker.estimates = []
                    for i in range(n):
                        order = workers if (i + r) % 2 == 0 else workers[::-1]
                        for worker in order:
                            if args.cold:
                                worker.ask("fresh")
                            answer = worker.ask(str(i))
                            worker.ms[r][i] = float(answer.pop("ms"))  # type: ignore[arg-type]
                            worker.estimates.append(answer)
                        bar.update()
        finally:
            for worker in workers:
                worker.process.kill()
    report(args, workers, frames.description)


def report(args: argparse.Namespace, workers: list[Worker], name: str) -> None:
    base, new = workers
    best = {w.name: np.min(np.asarray(w.ms), axis=0) for w in workers}
    stats = {k: percentiles(v) for k, v in best.items()}
    ratio = {p: stats["new"][p] / stats["base"][p] for p in stats["base"]}
    per_frame = float(np.median(best["new"] / best["base"]))
    close = apart(base.estimates, new.estimates)
    print(f"{name}, {'cold' if args.cold else 'tracking'}; least of {args.repeat} runs a frame")
    print(f"{'version':<28}{'p50 ms':>9}{'p95 ms':>9}{'p99 ms':>9}{'max ms':>9}")
    columns = ("p50", "p95", "p99", "max")
    for key, rev in (("base", args.base), ("new", args.new)):
        print(f"{key + ' (' + rev + ')':<28}" + "".join(f"{stats[key][p]:9.3f}" for p in columns))
    print(f"{'new / base':<28}" + "".join(f"{ratio[p]:9.3f}" for p in columns))
    print(f"median of the per-frame ratios: {per_frame:.3f}")
    print(
        f"estimates: pose on one and not the other on {close['frames_valid_differs']} frames; "
        f"apart by up to {close['position_m']:.2e} m, {close['yaw_rad']:.2e} rad, "
        f"covariance {close['covariance_relative']:.2e} of its size"
    )
    if args.json is not None:
        body = {
            "frames": name,
            "base": args.base,
            "new": args.new,
            "cold": args.cold,
            "repeat": args.repeat,
            "ms": stats,
            "new_over_base": ratio,
            "per_frame_ratio_median": per_frame,
            "estimates_apart": close,
            "ms_per_frame": {k: v.tolist() for k, v in best.items()},
        }
        args.json.write_text(json.dumps(body, indent=2))


if __name__ == "__main__":
    main()

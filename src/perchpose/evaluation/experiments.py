"""The paper's experiments on rendered frames: ranges, Table 1, Table 2, the dropout, the fusion
fit and ablations. Each function renders its own frames from a seeded generator and returns
plain results; the report module writes them out."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from perchpose.detection.detector import CornerMethod, MarkerDetector
from perchpose.estimator import PerchingEstimator
from perchpose.evaluation.fusion_fit import fit_sigma_least_squares, fit_sigma_lms
from perchpose.fusion.paper import FusionSigmas
from perchpose.geometry import facing_pose, wrap_angle_deg, yaw_rad
from perchpose.pose.marker import rotation_angle_rad
from perchpose.sim.render import ImageQuality, Renderer
from perchpose.sim.scenarios import Scenario, markers_in_view
from perchpose.sim.sequence import render_frame
from perchpose.target import TargetSpec
from perchpose.values import Estimate, MarkerDetection, MarkerPose

Array = NDArray[np.float64]
Tick = Callable[[int], None]

# The paper's numbers, for side-by-side reporting.
PAPER_RANGES_CM = {"z1_outer_max": 115.0, "z2_inner_max": 25.0, "z3_outer_min": 15.0}
PAPER_TABLE1 = [
    ((0, 0, 24), (0.3, -0.3, 24.4), (0.3, -0.3, 0.4)),
    ((3, 5, 16), (2.6, 5.3, 16.4), (0.4, 0.3, 0.4)),
    ((5, 8, 11), (5.4, 8.4, 11.3), (0.4, 0.4, 0.3)),
    ((10, 12, 7), (10.5, 12.6, 7.2), (0.5, 0.6, 0.2)),
    ((6, -5, 18), (6.3, -5.4, 18.5), (0.3, -0.4, 0.5)),
]
PAPER_TABLE2 = [
    (175, 178, 3),
    (-160, -157, -3),
    (135, 137, 2),
    (90, 92, 2),
    (30, 31, 1),
    (10, 9, 1),
    (5, 5, 0),
    (0, 1, 0),
]
PAPER_SIGMAS = {"sigma_x": 0.275, "sigma_y": 0.306, "sigma_z": 0.728, "sigma_yaw": 0.469}
TABLE2_POSITION_CM = (0.0, 0.0, 20.0)


def _no_tick(_: int) -> None:
    return None


# --------------------------------------------------------------------------- detection ranges
@dataclass(frozen=True)
class RangeCurve:
    """Detection probability against distance for one image quality.

    distances_cm : (D,). probability : name -> (D,) for ``outer``, ``inner`` and ``fused``.
    """

    quality: str
    distances_cm: Array
    probability: dict[str, Array]

    def z_max_cm(self, name: str, level: float = 0.5) -> float:
        """Largest distance where the probability reaches ``level`` (NaN if none)."""
        ok = np.flatnonzero(self.probability[name] >= level)
        return float(self.distances_cm[ok[-1]]) if ok.size else math.nan

    def z_min_cm(self, name: str, level: float = 0.5) -> float:
        """Smallest distance where the probability reaches ``level`` (NaN if none)."""
        ok = np.flatnonzero(self.probability[name] >= level)
        return float(self.distances_cm[ok[0]]) if ok.size else math.nan


def range_pose(z_m: float, rng: np.random.Generator) -> Array:
    """A pose at distance ``z_m`` near the optical axis, random heading and small tilts."""
    lateral = 0.08 * z_m
    return facing_pose(
        float(rng.uniform(-lateral, lateral)),
        float(rng.uniform(-lateral, lateral)),
        z_m,
        float(rng.uniform(-math.pi, math.pi)),
        float(np.radians(rng.uniform(-5, 5))),
        float(np.radians(rng.uniform(-5, 5))),
    )


def detection_ranges(
    renderer: Renderer[TargetSpec],
    quality_name: str,
    quality: ImageQuality,
    distances_cm: Array,
    frames: int,
    rng: np.random.Generator,
    tick: Tick = _no_tick,
) -> RangeCurve:
    """Fraction of single frames in which each marker gives a pose, per distance."""
    est = PerchingEstimator(renderer.camera, renderer.target, use_filter=False)
    names = ("outer", "inner", "fused")
    counts = {n: np.zeros(len(distances_cm)) for n in names}
    for d, z_cm in enumerate(distances_cm):
        for _ in range(frames):
            image = renderer.render(range_pose(float(z_cm) / 100.0, rng), quality, rng)
            est.reset()
            e = est.update(image, 0.0)
            counts["outer"][d] += e.markers[0].measurement is not None
            counts["inner"][d] += any(m.measurement is not None for m in e.markers[1:])
            counts["fused"][d] += e.valid
            tick(1)
    return RangeCurve(
        quality_name,
        np.asarray(distances_cm, np.float64),
        {n: c / frames for n, c in counts.items()},
    )


# --------------------------------------------------------------------------- static tables
@dataclass(frozen=True)
class StaticRow:
    """One static pose held for several frames, the filter running.

    actual : (x_cm, y_cm, z_cm, yaw_deg). estimated : mean over valid frames (NaN if none).
    error : estimated - actual. peak_to_peak : max - min of the per-frame estimate.
    max_abs_error : largest per-frame |error|. in_view : which markers are fully in the image.
    """

    actual: tuple[float, float, float, float]
    estimated: tuple[float, float, float, float]
    error: tuple[float, float, float, float]
    peak_to_peak: tuple[float, float, float, float]
    max_abs_error: tuple[float, float, float, float]
    valid_frames: int
    frames: int
    in_view: tuple[bool, ...]
    stages: tuple[int, ...]


def _quad(values: Array) -> tuple[float, float, float, float]:
    return (float(values[0]), float(values[1]), float(values[2]), float(values[3]))


def static_row(
    renderer: Renderer[TargetSpec],
    quality: ImageQuality,
    T: Array,
    frames: int,
    rng: np.random.Generator,
    fps: float = 30.0,
    tick: Tick = _no_tick,
) -> StaticRow:
    """Hold ``T`` for ``frames`` frames through a fresh estimator and summarise."""
    actual = np.array(
        [T[0, 3] * 100, T[1, 3] * 100, T[2, 3] * 100, math.degrees(yaw_rad(T[:3, :3]))]
    )
    est = PerchingEstimator(renderer.camera, renderer.target)
    values, stages = [], set()
    for k in range(frames):
        e = est.update(renderer.render(T, quality, rng), k / fps)
        tick(1)
        if e.valid:
            values.append([e.x_cm, e.y_cm, e.z_cm, e.yaw_deg])
            stages.add(e.stage)
    in_view = markers_in_view(renderer.camera, renderer.target, T)
    if not values:
        nan4 = (math.nan,) * 4
        return StaticRow(_quad(actual), nan4, nan4, nan4, nan4, 0, frames, in_view, ())
    v = np.array(values)
    err = v - actual
    err[:, 3] = [wrap_angle_deg(a) for a in err[:, 3]]
    mean = v.mean(axis=0)
    mean[3] = actual[3] + float(np.mean(err[:, 3]))
    mean[3] = wrap_angle_deg(mean[3])
    mean_err = err.mean(axis=0)
    p2p = err.max(axis=0) - err.min(axis=0)
    return StaticRow(
        _quad(actual),
        _quad(mean),
        _quad(mean_err),
        _quad(p2p),
        _quad(np.abs(err).max(axis=0)),
        len(values),
        frames,
        in_view,
        tuple(sorted(stages)),
    )


def table1(
    renderer: Renderer[TargetSpec],
    quality: ImageQuality,
    frames: int,
    rng: np.random.Generator,
    tick: Tick = _no_tick,
) -> list[StaticRow]:
    """The paper's five positions, target facing the camera with heading 0."""
    return [
        static_row(
            renderer, quality, facing_pose(x / 100, y / 100, z / 100, 0.0), frames, rng, tick=tick
        )
        for (x, y, z), _, _ in PAPER_TABLE1
    ]


def table2(
    renderer: Renderer[TargetSpec],
    quality: ImageQuality,
    frames: int,
    rng: np.random.Generator,
    tick: Tick = _no_tick,
) -> list[StaticRow]:
    """The paper's eight headings at TABLE2_POSITION_CM."""
    x, y, z = TABLE2_POSITION_CM
    return [
        static_row(
            renderer,
            quality,
            facing_pose(x / 100, y / 100, z / 100, math.radians(heading)),
            frames,
            rng,
            tick=tick,
        )
        for heading, _, _ in PAPER_TABLE2
    ]


# --------------------------------------------------------------------------- sequences
@dataclass(frozen=True)
class SequenceRun:
    """An estimator run over a rendered sequence.

    truth, filtered : (N, 4) x_cm, y_cm, z_cm, yaw_deg (filtered NaN where not valid).
    raw : marker index -> (N, 4) raw per-frame measurement (NaN where none).
    flips : per-marker measurements that took the wrong one of IPPE's two solutions (the other
        was closer to the true rotation by over 5 deg).
    """

    t_s: Array
    truth: Array
    filtered: Array
    raw: dict[int, Array]
    valid: NDArray[np.bool_]
    stage: NDArray[np.int64]
    dropout: NDArray[np.bool_]
    truth_in_view: NDArray[np.bool_]
    flips: int = 0

    def errors(self) -> Array:
        """(N, 4) filtered - truth, yaw wrapped."""
        e = self.filtered - self.truth
        e[:, 3] = np.array([wrap_angle_deg(a) if math.isfinite(a) else math.nan for a in e[:, 3]])
        return e


def truth_table(scenario: Scenario) -> Array:
    """(N, 4) truth x_cm, y_cm, z_cm, yaw_deg of a scenario."""
    return np.array(
        [
            [T[0, 3] * 100, T[1, 3] * 100, T[2, 3] * 100, math.degrees(yaw_rad(T[:3, :3]))]
            for T in scenario.poses
        ]
    )


def render_scenario(
    renderer: Renderer[TargetSpec],
    scenario: Scenario,
    rng: np.random.Generator,
    tick: Tick = _no_tick,
) -> list[NDArray[np.uint8]]:
    """All frames of ``scenario`` in memory."""
    frames = []
    for i in range(len(scenario)):
        frames.append(render_frame(renderer, scenario, i, rng))
        tick(1)
    return frames


def detect_all(
    renderer: Renderer[TargetSpec],
    frames: list[NDArray[np.uint8]],
    corners: CornerMethod = "edges",
) -> list[tuple[MarkerDetection, ...]]:
    """One detection pass over every frame, to share between estimator variants."""
    detector = MarkerDetector(renderer.camera, renderer.target, corners)
    return [detector.detect(f).markers for f in frames]


def run_sequence(
    estimator: PerchingEstimator,
    scenario: Scenario,
    frames: list[NDArray[np.uint8]] | list[tuple[MarkerDetection, ...]],
) -> SequenceRun:
    """Run ``estimator`` over pre-rendered ``frames`` of ``scenario``, or over their
    detections."""
    n = len(scenario)
    n_markers = len(estimator.target.markers)
    filtered = np.full((n, 4), np.nan)
    raw = {i: np.full((n, 4), np.nan) for i in range(n_markers)}
    valid = np.zeros(n, bool)
    stage = np.zeros(n, np.int64)
    flips = 0
    for k in range(n):
        frame = frames[k]
        t_s = float(scenario.t_s[k])
        e: Estimate = (
            estimator.update_detections(frame, t_s)
            if isinstance(frame, tuple)
            else estimator.update(frame, t_s)
        )
        valid[k] = e.valid
        stage[k] = e.stage
        if e.valid:
            filtered[k] = [e.x_cm, e.y_cm, e.z_cm, e.yaw_deg]
        for i, m in enumerate(e.markers):
            if m.measurement is not None:
                t = m.measurement.t_m * 100
                raw[i][k] = [t[0], t[1], t[2], math.degrees(m.measurement.yaw_rad)]
                flips += int(_wrong_branch(m.measurement, scenario.poses[k]))
    in_view = (
        np.array(
            [any(markers_in_view(estimator.camera, estimator.target, T)) for T in scenario.poses]
        )
        & ~scenario.dropout
    )
    return SequenceRun(
        scenario.t_s,
        truth_table(scenario),
        filtered,
        raw,
        valid,
        stage,
        scenario.dropout.copy(),
        in_view,
        flips,
    )


def _wrong_branch(measurement: MarkerPose, T_true: Array) -> bool:
    """The measurement took the IPPE solution farther from the true rotation (by over 5 deg:
    near head-on the two solutions lie a degree or two apart and either is right)."""
    alt = measurement.alt_T_camera_target
    if alt is None:
        return False
    chosen = rotation_angle_rad(measurement.T_camera_target[:3, :3], T_true[:3, :3])
    other = rotation_angle_rad(alt[:3, :3], T_true[:3, :3])
    return chosen > other + math.radians(5.0)


MOVE_WAYPOINTS = np.array(
    [
        [0.0, 0.0, 0.60, 0.0],
        [0.06, -0.04, 0.45, 25.0],
        [-0.05, 0.03, 0.35, -20.0],
        [0.03, 0.05, 0.55, 40.0],
        [-0.04, -0.03, 0.40, 5.0],
        [0.0, 0.0, 0.50, -30.0],
    ]
)  # x_m, y_m, z_m, yaw_deg


def moves_scenario(
    duration_s: float,
    dropout_at_s: float,
    dropout_s: float,
    quality: ImageQuality,
    fps: float = 30.0,
    segment_s: float = 3.0,
) -> Scenario:
    """The Kalman figure's sequence: the camera moved between positions 35-60 cm below the
    target, ``segment_s`` per move (a smooth move over 70 % of it, then a pause), with one
    dropout."""
    n = int(round(duration_s * fps))
    t = np.arange(n) / fps
    poses = []
    for ti in t:
        k = int(ti // segment_s)
        a = MOVE_WAYPOINTS[k % len(MOVE_WAYPOINTS)]
        b = MOVE_WAYPOINTS[(k + 1) % len(MOVE_WAYPOINTS)]
        u = (ti - k * segment_s) / segment_s
        s = 0.5 - 0.5 * math.cos(math.pi * min(1.0, u / 0.7))
        p = a + s * (b - a)
        poses.append(facing_pose(p[0], p[1], p[2], math.radians(p[3])))
    dropout = (t >= dropout_at_s) & (t < dropout_at_s + dropout_s)
    return Scenario("moves", t, np.stack(poses), dropout, quality)


@dataclass(frozen=True)
class DropoutResult:
    """The filter across one dropout."""

    dropout_frames: int
    frames_coasted: int
    max_position_error_cm: float
    max_yaw_error_deg: float
    max_position_error_before_cm: float
    wrong_branch: int = 0


def dropout_summary(run: SequenceRun) -> DropoutResult:
    """Errors of the valid frames inside the dropout, and in the second before it."""
    err = run.errors()
    pos = np.linalg.norm(err[:, :3], axis=1)
    inside = run.dropout & run.valid
    first = int(np.flatnonzero(run.dropout)[0]) if run.dropout.any() else len(run.t_s)
    before = np.zeros_like(run.valid)
    before[max(0, first - 30) : first] = True
    before &= run.valid

    def peak(values: Array, mask: NDArray[np.bool_]) -> float:
        return float(np.nanmax(np.abs(values[mask]))) if mask.any() else math.nan

    return DropoutResult(
        int(run.dropout.sum()),
        int(inside.sum()),
        peak(pos, inside),
        peak(err[:, 3], inside),
        peak(pos, before),
        run.flips,
    )


# --------------------------------------------------------------------------- fusion fit
@dataclass(frozen=True)
class FusionSamples:
    """Frames where both markers were measured: (N, 4) x_cm, y_cm, z_cm, yaw_deg each."""

    truth: Array
    outer: Array
    inner: Array
    position_index: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64))

    def rms_errors(self) -> dict[str, tuple[float, float]]:
        """Each component's rms error against the truth: (outer, inner), cm or deg."""
        out = {}
        for k, name in enumerate(COMPONENT_NAMES):
            errors = []
            for marker in (self.outer, self.inner):
                e = marker[:, k] - self.truth[:, k]
                if k == 3:  # yaw, on the circle
                    e = (e + 180.0) % 360.0 - 180.0
                errors.append(float(np.sqrt(np.mean(e * e))))
            out[name] = (errors[0], errors[1])
        return out


@dataclass(frozen=True)
class FusionFit:
    """Sigma per component from closed-form least squares and from the iterative LMS."""

    least_squares: dict[str, float]
    lms: dict[str, float]
    lms_passes: dict[str, int]
    samples: int

    @property
    def at_bounds(self) -> list[str]:
        """The components whose least-squares weight sits at 0 or 1: there the data say one
        marker alone does best, which is no fit of the two markers' noise."""
        return [name for name, v in self.least_squares.items() if min(v, 1.0 - v) < 1e-6]

    def sigmas(self, method: str = "least_squares") -> FusionSigmas:
        """The fitted weights (``least_squares`` or ``lms``) as the paper's fusion takes them."""
        fitted = self.least_squares if method == "least_squares" else self.lms
        return FusionSigmas(
            x=fitted["sigma_x"], y=fitted["sigma_y"], z=fitted["sigma_z"], yaw=fitted["sigma_yaw"]
        )


def fusion_samples(
    renderer: Renderer[TargetSpec],
    quality: ImageQuality,
    positions: int,
    frames: int,
    rng: np.random.Generator,
    z_range_m: tuple[float, float],
    tick: Tick = _no_tick,
) -> FusionSamples:
    """The paper's protocol: random positions and headings, ``frames`` frames each, raw
    per-marker measurements where both markers give a pose, as the paper's fusion takes them
    (every small marker with its pattern fit)."""
    est = PerchingEstimator(renderer.camera, renderer.target, use_filter=False, fusion="paper")
    truth, outer, inner, index = [], [], [], []
    for p in range(positions):
        z = float(rng.uniform(*z_range_m))
        T = facing_pose(
            float(rng.uniform(-0.1, 0.1) * z),
            float(rng.uniform(-0.1, 0.1) * z),
            z,
            float(rng.uniform(-math.pi, math.pi)),
        )
        actual = [T[0, 3] * 100, T[1, 3] * 100, T[2, 3] * 100, math.degrees(yaw_rad(T[:3, :3]))]
        est.reset()
        for k in range(frames):
            e = est.update(renderer.render(T, quality, rng), k / 30)
            tick(1)
            m0, m1 = e.markers[0].measurement, e.markers[1].measurement
            if m0 is None or m1 is None:
                continue
            truth.append(actual)
            outer.append([*(m0.t_m * 100), math.degrees(m0.yaw_rad)])
            inner.append([*(m1.t_m * 100), math.degrees(m1.yaw_rad)])
            index.append(p)
    return FusionSamples(
        np.array(truth).reshape(-1, 4),
        np.array(outer).reshape(-1, 4),
        np.array(inner).reshape(-1, 4),
        np.array(index, np.int64),
    )


COMPONENT_NAMES = ("sigma_x", "sigma_y", "sigma_z", "sigma_yaw")


def fit_fusion(samples: FusionSamples) -> FusionFit:
    """Fit sigma_x, sigma_y, sigma_z, sigma_yaw both ways."""
    if samples.truth.shape[0] < 2:
        raise ValueError("fewer than 2 frames with both markers measured")
    ls, lms, passes = {}, {}, {}
    for k, name in enumerate(COMPONENT_NAMES):
        circular = k == 3
        scale = math.pi / 180 if circular else 1.0
        a, b, t = (
            samples.outer[:, k] * scale,
            samples.inner[:, k] * scale,
            samples.truth[:, k] * scale,
        )
        ls[name] = fit_sigma_least_squares(a, b, t, circular)
        lms[name], passes[name] = fit_sigma_lms(a, b, t, circular)
    return FusionFit(ls, lms, passes, int(samples.truth.shape[0]))


# --------------------------------------------------------------------------- ablations
ABLATIONS: dict[str, dict[str, object]] = {
    "paper (both markers, filter)": {"markers": None, "use_filter": True},
    "outer only, filter": {"markers": (0,), "use_filter": True},
    "inner only, filter": {"markers": (1,), "use_filter": True},
    "both markers, no filter": {"markers": None, "use_filter": False},
    "outer only, no filter": {"markers": (0,), "use_filter": False},
    "inner only, no filter": {"markers": (1,), "use_filter": False},
    "paper with cornerSubPix corners": {"markers": None, "use_filter": True, "corners": "subpix"},
    "covariance fusion, filter": {"markers": None, "use_filter": True, "fusion": "covariance"},
    "covariance fusion, no filter": {"markers": None, "use_filter": False, "fusion": "covariance"},
    "covariance fusion with cornerSubPix corners": {
        "markers": None,
        "use_filter": True,
        "fusion": "covariance",
        "corners": "subpix",
    },
}


@dataclass(frozen=True)
class AblationRow:
    """One variant on the approach: coverage and errors over frames with the target in view.

    p95_relative_error_pct : 95th percentile of the position error as a share of the distance.
    max_jump_cm : largest change of the position error between consecutive frames with an
        estimate (a step of the estimate that the target's motion does not explain; far away
        on noisy images, frame-to-frame noise sets it).
    handover_jump_cm : the same, only where a marker enters or leaves the measurement.
    flips : marker measurements on the wrong IPPE solution (``SequenceRun.flips``).
    """

    name: str
    coverage: float
    median_position_error_cm: float
    p95_position_error_cm: float
    median_yaw_error_deg: float
    p95_yaw_error_deg: float
    p95_relative_error_pct: float
    max_jump_cm: float
    handover_jump_cm: float
    flips: int
    run: SequenceRun


def ablation(
    renderer: Renderer[TargetSpec],
    scenario: Scenario,
    detections: list[tuple[MarkerDetection, ...]],
    name: str,
    options: dict[str, object],
) -> AblationRow:
    """Run one variant over the same detections of the same rendered frames."""
    markers = options["markers"]
    est = PerchingEstimator(
        renderer.camera,
        renderer.target,
        markers=markers if isinstance(markers, tuple) else None,
        use_filter=bool(options["use_filter"]),
        fusion="covariance" if options.get("fusion") == "covariance" else "paper",
        corners="subpix" if options.get("corners") == "subpix" else "edges",
    )
    run = run_sequence(est, scenario, detections)
    err = run.errors()
    sel = run.truth_in_view & run.valid
    pos = np.linalg.norm(err[sel, :3], axis=1)
    yaw = np.abs(err[sel, 3])

    def pct(values: Array, q: float) -> float:
        return float(np.percentile(values, q)) if values.size else math.nan

    coverage = float(sel.sum() / max(1, run.truth_in_view.sum()))
    relative = 100.0 * pos / np.maximum(np.abs(run.truth[sel, 2]), 1e-6)
    steps = np.flatnonzero(sel[1:] & sel[:-1])
    jumps = np.linalg.norm(err[steps + 1, :3] - err[steps, :3], axis=1)
    measured = np.stack([np.isfinite(raw[:, 0]) for raw in run.raw.values()], axis=1)
    handover = np.any(measured[steps + 1] != measured[steps], axis=1)
    return AblationRow(
        name,
        coverage,
        pct(pos, 50),
        pct(pos, 95),
        pct(yaw, 50),
        pct(yaw, 95),
        pct(relative, 95),
        float(jumps.max()) if jumps.size else math.nan,
        float(jumps[handover].max()) if np.any(handover) else 0.0,
        run.flips,
        run,
    )

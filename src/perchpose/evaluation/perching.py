"""Perching campaigns as results: success rates with their confidence intervals, failure
causes, percentiles, and the files a campaign writes.

``runs.csv`` gets one row per run as each run finishes (``CampaignLog``), so a killed campaign
keeps every finished run and ``--resume`` carries on from them; ``campaign.json`` records the
setup the rows belong to. ``perch.json`` (the figures), ``perch.md`` (a table per wind level and
estimator), ``trajectories.png`` and, for a wind sweep, ``wind.png`` are written from the rows.
"""

from __future__ import annotations

import csv
import hashlib
import json
import math
from collections import Counter
from collections.abc import Callable, Iterable, Iterator
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TextIO

import numpy as np

from perchpose.errors import CampaignError
from perchpose.evaluation.plots import perch_figure, sweep_figure
from perchpose.pose.marker import rotation_angle_rad
from perchpose.sim.perch import (
    CONTACT_RADIUS_MM,
    FALL_M,
    OFFSET_AT_S,
    REASONS,
    PerchResult,
    PerchSetup,
)
from perchpose.sim.sensing import SensingDraw

RUN_COLUMNS = (
    "estimator",
    "wind",
    "wind_mean_mps",
    "turbulence_sigma_mps",
    "seed",
    "success",
    "reason",
    "contact_offset_mm",
    "contact_speed_mps",
    "time_to_perch_s",
    "tries",
    "wind_direction_deg",
    "latency_set_ms",
    "contact_first",
    "contact_tilt_deg",
    "contact_lateral_speed_mps",
    "contact_vertical_speed_mps",
    "fault",
    "fault_start_s",
    "fault_duration_s",
    "motor_stop_height_m",
    "max_setpoint_gap_s",
    "pilot_states",
    "time_offset_ms",
    "time_offset_sigma_ms",
    "time_offset_true_ms",
    "time_offset_end_ms",
    "time_offset_end_true_ms",
    "seated_offset_mm",
    "stop_after_contact_s",
    "seat_drops",
    "leans_refused",
    "latency_ms",
    "odometry_hz",
    "odometry_delay_ms",
    "attitude_delay_ms",
    "clock_offset_ms",
    "focal_scale",
    "principal_point_shift_px",
    "mount_error_deg",
    "mount_error_mm",
    "target_scale",
    "latency_configured_ms",
    "uplink_delay_ms",
)
SENSE_COLUMNS = RUN_COLUMNS[RUN_COLUMNS.index("latency_ms") :]
OFFSET_GOAL_MS = 10.0  # the time-offset estimate's goal: this near the truth after 3 s (p95)


RunKey = tuple[str, str, float, float, str, int]
Cell = tuple[str, str, str]  # wind, estimator, latency label


def run_key(setup: PerchSetup, seed: int) -> RunKey:
    """The key of the run ``setup`` flies with ``seed`` (``RunRecord.key`` of its record)."""
    level = setup.wind_level
    return (
        setup.estimator,
        setup.wind,
        level.mean_mps,
        level.turbulence_sigma_mps,
        setup.latency_label,
        seed,
    )


@dataclass(frozen=True)
class RunRecord:
    """One finished run, as ``runs.csv`` holds it."""

    estimator: str
    wind: str
    wind_mean_mps: float
    turbulence_sigma_mps: float
    seed: int
    success: bool
    reason: str
    contact_offset_mm: float
    contact_speed_mps: float
    time_to_perch_s: float
    tries: int
    wind_direction_deg: float
    latency_set_ms: str = ""  # the cell's latency (PerchSetup.latency_label)
    contact_first: str = ""
    contact_tilt_deg: float = math.nan
    contact_lateral_speed_mps: float = math.nan
    contact_vertical_speed_mps: float = math.nan
    fault: str = ""  # the fault injected (empty: none), from when, for how long
    fault_start_s: float = math.nan
    fault_duration_s: float = math.nan
    motor_stop_height_m: float = math.nan  # above what it rests on (NaN: not stopped)
    max_setpoint_gap_s: float = math.nan
    pilot_states: str = ""  # state@t;... as the pilot entered them
    # the time-offset estimate after OFFSET_AT_S of flight (its spread, its truth), at the end
    time_offset_ms: float = math.nan
    time_offset_sigma_ms: float = math.nan
    time_offset_true_ms: float = math.nan
    time_offset_end_ms: float = math.nan
    time_offset_end_true_ms: float = math.nan
    # where the magnet's centre sat when the perch was judged; the first contact to the
    # motors' stop (NaN: not flown through the contact, or no stop against the plate)
    seated_offset_mm: float = math.nan
    stop_after_contact_s: float = math.nan
    # checks of the magnet's hold the vehicle came down in; the pilot sent velocities instead
    # of leans the vehicle did not fly (``control.lean_follow``)
    seat_drops: int = 0
    leans_refused: bool = False
    senses: tuple[float, ...] = ()  # SENSE_COLUMNS' values (empty: ideal senses)

    @staticmethod
    def of(result: PerchResult, setup: PerchSetup) -> RunRecord:
        level = setup.wind_level
        touch = result.contact
        fault = result.fault
        return RunRecord(
            result.estimator,
            setup.wind,
            level.mean_mps,
            level.turbulence_sigma_mps,
            result.seed,
            result.success,
            result.reason,
            result.contact_offset_mm,
            result.contact_speed_mps,
            result.time_to_perch_s,
            result.tries,
            math.degrees(result.wind_direction_rad),
            setup.latency_label,
            touch.part if touch is not None else "",
            touch.tilt_deg if touch is not None else math.nan,
            touch.lateral_speed_mps if touch is not None else math.nan,
            touch.v_mps[2] if touch is not None else math.nan,
            fault.kind if fault is not None else "",
            fault.start_s if fault is not None else math.nan,
            fault.duration_s if fault is not None else math.nan,
            result.motor_stop_height_m,
            result.max_setpoint_gap_s,
            result.pilot_states,
            result.time_offset.offset_s * 1000.0,
            result.time_offset.sigma_s * 1000.0,
            result.time_offset.true_s * 1000.0,
            result.time_offset_end.offset_s * 1000.0,
            result.time_offset_end.true_s * 1000.0,
            result.seated_offset_mm,
            result.stop_after_contact_s,
            result.seat_drops,
            result.leans_refused,
            sense_values(result.senses, setup),
        )

    @property
    def key(self) -> RunKey:
        """What identifies a run: estimator, wind, latency and seed."""
        return (
            self.estimator,
            self.wind,
            self.wind_mean_mps,
            self.turbulence_sigma_mps,
            self.latency_set_ms,
            self.seed,
        )

    def row(self) -> list[str]:
        return [
            self.estimator,
            self.wind,
            f"{self.wind_mean_mps:g}",
            f"{self.turbulence_sigma_mps:g}",
            str(self.seed),
            str(int(self.success)),
            self.reason,
            f"{self.contact_offset_mm:.3f}",
            f"{self.contact_speed_mps:.4f}",
            f"{self.time_to_perch_s:.3f}",
            str(self.tries),
            f"{self.wind_direction_deg:.1f}",
            self.latency_set_ms,
            self.contact_first,
            f"{self.contact_tilt_deg:.2f}",
            f"{self.contact_lateral_speed_mps:.4f}",
            f"{self.contact_vertical_speed_mps:.4f}",
            self.fault,
            f"{self.fault_start_s:.3f}",
            f"{self.fault_duration_s:.3f}",
            f"{self.motor_stop_height_m:.4f}",
            f"{self.max_setpoint_gap_s:.4f}",
            self.pilot_states,
            f"{self.time_offset_ms:.3f}",
            f"{self.time_offset_sigma_ms:.3f}",
            f"{self.time_offset_true_ms:.3f}",
            f"{self.time_offset_end_ms:.3f}",
            f"{self.time_offset_end_true_ms:.3f}",
            f"{self.seated_offset_mm:.3f}",
            f"{self.stop_after_contact_s:.3f}",
            str(self.seat_drops),
            str(int(self.leans_refused)),
            *(f"{v:.6g}" for v in (self.senses or (math.nan,) * len(SENSE_COLUMNS))),
        ]

    @staticmethod
    def from_row(row: dict[str, str], where: str) -> RunRecord:
        try:
            return RunRecord(
                row["estimator"],
                row["wind"],
                float(row["wind_mean_mps"]),
                float(row["turbulence_sigma_mps"]),
                int(row["seed"]),
                row["success"] == "1",
                row["reason"],
                float(row["contact_offset_mm"]),
                float(row["contact_speed_mps"]),
                float(row["time_to_perch_s"]),
                int(row["tries"]),
                float(row["wind_direction_deg"]),
                row["latency_set_ms"],
                row["contact_first"],
                float(row["contact_tilt_deg"]),
                float(row["contact_lateral_speed_mps"]),
                float(row["contact_vertical_speed_mps"]),
                row["fault"],
                float(row["fault_start_s"]),
                float(row["fault_duration_s"]),
                float(row["motor_stop_height_m"]),
                float(row["max_setpoint_gap_s"]),
                row["pilot_states"],
                float(row["time_offset_ms"]),
                float(row["time_offset_sigma_ms"]),
                float(row["time_offset_true_ms"]),
                float(row["time_offset_end_ms"]),
                float(row["time_offset_end_true_ms"]),
                float(row.get("seated_offset_mm", "nan")),
                float(row.get("stop_after_contact_s", "nan")),
                int(row.get("seat_drops", "0")),
                row.get("leans_refused", "0") == "1",
                tuple(float(row[name]) for name in SENSE_COLUMNS),
            )
        except (KeyError, ValueError, TypeError) as exc:
            raise CampaignError(f"{where}: not a perchpose runs.csv row ({exc})") from exc


def wilson_interval(successes: int, n: int, z: float = 1.959964) -> tuple[float, float]:
    """The Wilson score interval of a binomial proportion (95 % by default)."""
    if n <= 0:
        return (0.0, 1.0)
    p = successes / n
    denominator = 1 + z * z / n
    centre = (p + z * z / (2 * n)) / denominator
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / denominator
    return (max(0.0, centre - half), min(1.0, centre + half))


@dataclass(frozen=True)
class CampaignSummary:
    """Statistics of a set of runs of one estimator in one wind."""

    estimator: str
    wind: str
    runs: int
    success_rate: float
    success_interval: tuple[float, float]
    reasons: dict[str, int]
    contact_offset_mm: dict[str, float]
    contact_speed_mps: dict[str, float]
    time_to_perch_s: dict[str, float]


def _percentiles(values: Iterable[float]) -> dict[str, float]:
    finite = np.array([v for v in values if math.isfinite(v)])
    if finite.size == 0:
        return {"p50": math.nan, "p90": math.nan, "p95": math.nan, "max": math.nan}
    return {
        "p50": float(np.percentile(finite, 50)),
        "p90": float(np.percentile(finite, 90)),
        "p95": float(np.percentile(finite, 95)),
        "max": float(finite.max()),
    }


def summarise(records: list[RunRecord] | list[PerchResult]) -> CampaignSummary:
    """Success rate (with its Wilson interval), failure reasons and percentiles of contact
    offset, contact speed of the successes, and time to perch."""
    if not records:
        raise ValueError("no runs to summarise")
    wins = sum(r.success for r in records)
    first = records[0]
    return CampaignSummary(
        estimator=first.estimator,
        wind=first.wind if isinstance(first, RunRecord) else "",
        runs=len(records),
        success_rate=wins / len(records),
        success_interval=wilson_interval(wins, len(records)),
        reasons=dict(Counter(r.reason for r in records)),
        contact_offset_mm=_percentiles(r.contact_offset_mm for r in records),
        contact_speed_mps=_percentiles(r.contact_speed_mps for r in records if r.success),
        time_to_perch_s=_percentiles(r.time_to_perch_s for r in records if r.success),
    )


def sense_values(draw: SensingDraw | None, setup: PerchSetup) -> tuple[float, ...]:
    """A run's senses as ``SENSE_COLUMNS`` holds them (ideal: the setup's latency and
    odometry rate, no error)."""
    if draw is None:
        latency_ms = setup.latency_s * 1000.0
        return (
            latency_ms, setup.odometry_hz, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, latency_ms, 0.0
        )  # fmt: skip
    K, K_true = draw.camera.K, setup.camera.K
    mount = draw.T_true_believed
    angle = math.degrees(rotation_angle_rad(mount[:3, :3], np.eye(3)))
    return (
        draw.latency_s * 1000.0,
        draw.odometry_hz,
        draw.odometry_delay_s * 1000.0,
        draw.attitude_delay_s * 1000.0,
        draw.clock_offset_s * 1000.0,
        float(K[0, 0] / K_true[0, 0]),
        float(math.hypot(K[0, 2] - K_true[0, 2], K[1, 2] - K_true[1, 2])),
        angle,
        float(np.linalg.norm(mount[:3, 3]) * 1000.0),
        draw.target_scale,
        draw.latency_configured_s * 1000.0,
        draw.uplink_delay_s * 1000.0,
    )


def _latency_ms(setup: PerchSetup) -> float | list[float]:
    """The camera latency a campaign flew, ms: one value where it is fixed, the range
    ``[low, high]`` each run's is drawn from otherwise."""
    low, high = (round(v * 1000.0, 3) for v in setup.latency_range_s)
    return low if low == high else [low, high]


def setup_description(setup: PerchSetup) -> dict[str, object]:
    """What a campaign's runs depend on besides estimator, wind and seed."""
    c = setup.camera
    return {
        "camera": c.name,
        "camera_model": c.model,
        "image_px": [c.width_px, c.height_px],
        "K": np.asarray(c.K).round(6).tolist(),
        "fps": setup.fps,
        "latency_frames": setup.latency_frames,
        "latency_ms": _latency_ms(setup),
        "drop_probability": setup.drop_probability,
        "start_below_m": list(setup.start_below_m),
        "start_lateral_fraction": setup.start_lateral_fraction,
        "ceiling_effect": setup.ceiling_effect,
        "duration_s": setup.duration_s,
        "hover_s": setup.hover_s,
        "physics_hz": setup.physics_hz,
        "disturbances": asdict(setup.disturbances),
        "vehicle": asdict(setup.vehicle),
        "controller": {k: v for k, v in asdict(setup.controller).items() if k != "T_body_camera"},
        "contact": asdict(setup.contact),
        "sensing": asdict(setup.sensing),
        "stamps": setup.stamps,
        "faults": list(setup.faults),
        "contact_mode": setup.contact_mode,
        "magnet": asdict(setup.magnet),
        "surface": asdict(setup.surface),
        "flight_controller": setup.flight_controller,
        "onboard_estimator": setup.onboard_estimator,
        "command": setup.pilot.command,
        "T_body_camera": np.asarray(setup.controller.T_body_camera).round(9).tolist(),
        # a drag-free estimator's pilot holds its attitude to the gyro over this long
        **({"gyro_blend_s": setup.pilot.gyro_blend_s} if setup.pilot.lean_lag_s > 0 else {}),
    }


def _fingerprint(description: dict[str, object]) -> str:
    text = json.dumps(description, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def _lock_folder(out: Path) -> TextIO:
    """An exclusive lock on ``out`` (``campaign.lock``, released when the file is closed or
    the process ends): two campaigns writing one folder would count runs twice."""
    handle = (out / "campaign.lock").open("a", encoding="utf-8")
    try:
        import fcntl
    except ImportError:  # not POSIX: no lock to take
        return handle
    try:
        fcntl.flock(handle.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError as exc:
        handle.close()
        raise CampaignError(
            f"{out}: another perchpose campaign is writing here; wait for it to end or use "
            "another --out"
        ) from exc
    return handle


REPORTS = ("perch.json", "perch.md", "trajectories.png", "wind.png", "latency.png")


def _rows_in(path: Path) -> int:
    """The data rows of a ``runs.csv`` (0 when there is none)."""
    if not path.exists():
        return 0
    with path.open("rb") as f:
        return max(0, sum(1 for line in f if line.strip()) - 1)


class CampaignLog:
    """``runs.csv`` written a row at a time (flushed), with ``campaign.json`` naming the setup.

    resume : keep the rows already there (they must come from the same setup, which
    ``campaign.json`` names) and report which runs are done. overwrite : start afresh, the
    earlier rows and reports deleted. Neither, in a folder that holds runs: refused, so that
    no result is lost by a command run twice.
    """

    def __init__(
        self,
        out_dir: str | Path,
        setup: PerchSetup,
        *,
        resume: bool = False,
        overwrite: bool = False,
    ) -> None:
        self.out = Path(out_dir)
        if resume and overwrite:
            raise CampaignError("--resume keeps the runs and --overwrite deletes them: give one")
        try:
            self.out.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise CampaignError(f"{self.out}: cannot create the output folder ({exc})") from exc
        self._lock = _lock_folder(self.out)
        self.path = self.out / "runs.csv"
        try:
            self._check_folder(resume, overwrite)
        except CampaignError:
            self._release()
            raise
        description = setup_description(setup)
        fingerprint = _fingerprint(description)
        meta = self.out / "campaign.json"
        self.records: list[RunRecord] = []
        if resume:
            self.records = self._resumed(meta, fingerprint)
        meta.write_text(
            json.dumps({"fingerprint": fingerprint, "setup": description}, indent=2, default=str),
            encoding="utf-8",
        )
        fresh = not resume or not self.path.exists()
        self._file: TextIO = self.path.open("w" if fresh else "a", newline="", encoding="utf-8")
        self._writer = csv.writer(self._file)
        if fresh:
            self._writer.writerow(RUN_COLUMNS)
            self._file.flush()

    def _check_folder(self, resume: bool, overwrite: bool) -> None:
        """Refuse to lose runs; with ``overwrite``, delete the earlier rows' reports."""
        rows = _rows_in(self.path)
        meta = self.out / "campaign.json"
        if rows and not (resume or overwrite):
            raise CampaignError(
                f"{self.out} holds {rows} runs: --resume flies only the missing ones, "
                "--overwrite starts afresh, or give another --out"
            )
        if rows and resume and not meta.exists():
            raise CampaignError(
                f"{self.out}: --resume needs {meta.name}, which names the setup of the {rows} "
                "runs there, and it is missing: --overwrite starts afresh"
            )
        if overwrite:
            for name in REPORTS:
                (self.out / name).unlink(missing_ok=True)

    def _resumed(self, meta: Path, fingerprint: str) -> list[RunRecord]:
        if not meta.exists() or not self.path.exists():
            return []
        try:
            previous = json.loads(meta.read_text(encoding="utf-8"))["fingerprint"]
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise CampaignError(f"{meta}: not a perchpose campaign file ({exc})") from exc
        if previous != fingerprint:
            raise CampaignError(
                f"{self.out}: --resume found runs of another setup (camera, vehicle, controller "
                "or disturbances differ); use another --out or drop --resume"
            )
        records = list(read_runs(self.path))
        self._cut_partial_row()
        return records

    def _cut_partial_row(self) -> None:
        """A run killed mid-write leaves no half row behind the ones kept."""
        data = self.path.read_bytes()
        if data and not data.endswith(b"\n"):
            self.path.write_bytes(data[: data.rfind(b"\n") + 1])

    @property
    def done(self) -> set[RunKey]:
        return {r.key for r in self.records}

    def add(self, record: RunRecord) -> None:
        self.records.append(record)
        self._writer.writerow(record.row())
        self._file.flush()

    def _release(self) -> None:
        """Give up the folder's lock and remove its file."""
        self._lock.close()  # and with it the lock
        (self.out / "campaign.lock").unlink(missing_ok=True)

    def close(self) -> None:
        self._file.close()
        self._release()

    def __enter__(self) -> CampaignLog:
        return self

    def __exit__(self, *_: object) -> None:
        self.close()


def read_runs(path: str | Path) -> Iterator[RunRecord]:
    """The rows of a ``runs.csv``; a last row cut short by a killed run is skipped."""
    with Path(path).open(newline="", encoding="utf-8") as f:
        rows = list(csv.DictReader(f))
    for i, row in enumerate(rows, start=2):
        if None in row.values() or len(row) < len(RUN_COLUMNS):
            if i == len(rows) + 1:
                return  # the partial last line of a killed run
            raise CampaignError(f"{path}: line {i} is not a whole run")
        yield RunRecord.from_row(row, f"{path}: line {i}")


def group(records: list[RunRecord]) -> dict[Cell, list[RunRecord]]:
    """Runs by (wind, estimator, latency), each in seed order, cells in the order first met."""
    out: dict[Cell, list[RunRecord]] = {}
    for r in records:
        out.setdefault((r.wind, r.estimator, r.latency_set_ms), []).append(r)
    return {k: sorted(v, key=lambda r: r.seed) for k, v in out.items()}


def cell_names(groups: dict[Cell, list[RunRecord]]) -> dict[Cell, str]:
    """``wind/estimator``, with ``/latency ms`` where the campaign flew several latencies."""
    several = len({lat for _, _, lat in groups}) > 1
    return {(w, e, lat): f"{w}/{e}/{lat} ms" if several else f"{w}/{e}" for (w, e, lat) in groups}


def _clean(d: dict[str, float]) -> dict[str, float | None]:
    return {k: (v if math.isfinite(v) else None) for k, v in d.items()}


def _summary_dict(s: CampaignSummary, records: list[RunRecord]) -> dict[str, object]:
    return {
        "wind": s.wind,
        "wind_mean_mps": records[0].wind_mean_mps,
        "turbulence_sigma_mps": records[0].turbulence_sigma_mps,
        "success_rate": s.success_rate,
        "success_interval_95": list(s.success_interval),
        "runs": s.runs,
        "reasons": s.reasons,
        "contact_offset_mm": _clean(s.contact_offset_mm),
        "contact_speed_mps": _clean(s.contact_speed_mps),
        "time_to_perch_s": _clean(s.time_to_perch_s),
        "contact_tilt_deg": _clean(_percentiles(r.contact_tilt_deg for r in records)),
        "contact_lateral_speed_mps": _clean(
            _percentiles(r.contact_lateral_speed_mps for r in records)
        ),
        "contact_first": dict(Counter(r.contact_first or "none" for r in records)),
        "seated_offset_mm": _clean(_percentiles(r.seated_offset_mm for r in records)),
        "stop_after_contact_s": _clean(_percentiles(r.stop_after_contact_s for r in records)),
        "seat_drops": sum(r.seat_drops for r in records),
        "runs_with_seat_drops": sum(r.seat_drops > 0 for r in records),
        "leans_refused": sum(r.leans_refused for r in records),
        "time_offset": time_offset_summary(records),
    }


def time_offset_summary(records: list[RunRecord]) -> dict[str, object]:
    """How well the online time-offset estimate found the truth after ``OFFSET_AT_S`` of
    flight: how many runs had one then, the error's percentiles (|estimate - truth|, ms),
    how many were within ``OFFSET_GOAL_MS``, and the true offsets' size in those runs (what
    no correction at all would be off by)."""
    found = [r for r in records if math.isfinite(r.time_offset_ms)]
    errors = [abs(r.time_offset_ms - r.time_offset_true_ms) for r in found]
    truths = [abs(r.time_offset_true_ms) for r in records if math.isfinite(r.time_offset_true_ms)]
    return {
        "at_s": OFFSET_AT_S,
        "runs_with_estimate": len(found),
        "error_ms": _clean(_percentiles(errors)),
        "within_goal": sum(e <= OFFSET_GOAL_MS for e in errors),
        "goal_ms": OFFSET_GOAL_MS,
        "true_offset_abs_ms": _clean(_percentiles(truths)),
        "sigma_ms": _clean(_percentiles(r.time_offset_sigma_ms for r in found)),
    }


def summary_json(records: list[RunRecord], setup: PerchSetup) -> dict[str, object]:
    """The figures of a campaign: per wind and estimator (``cells``), per estimator at the
    campaign's own wind (``by_estimator``), and the first estimator's at the top level
    (``success_rate``, ``runs``, ``contact_offset_mm``, ``time_to_perch_s``,
    ``wind_mean_mps``, ``turbulence_sigma_mps``)."""
    if not records:
        raise CampaignError("the campaign has no finished runs")
    groups = group(records)
    names = cell_names(groups)
    cells = {names[key]: _summary_dict(summarise(rs), rs) for key, rs in groups.items()}
    first_wind, _, first_latency = next(iter(groups))
    by_estimator = {
        e: cells[names[(w, e, lat)]]
        for (w, e, lat) in groups
        if (w, lat) == (first_wind, first_latency)
    }
    top = next(iter(by_estimator.values()))
    first_name = next(iter(by_estimator))
    first_cell = names[(first_wind, first_name, first_latency)]
    return {
        "top_level": f"the figures at this level are the cell {first_cell}'s "
        "(the first wind, estimator and latency flown); every cell is under 'cells', every "
        f"estimator at the first wind and latency under 'by_estimator'",
        "estimator": first_name,
        "wind": first_wind,
        "wind_mean_mps": top["wind_mean_mps"],
        "turbulence_sigma_mps": top["turbulence_sigma_mps"],
        "success_rate": top["success_rate"],
        "success_interval_95": top["success_interval_95"],
        "runs": top["runs"],
        "contact_offset_mm": top["contact_offset_mm"],
        "time_to_perch_s": top["time_to_perch_s"],
        "sensing": setup.sensing.name,
        "odometry": None if setup.sensing.is_ideal else setup.sensing.odometry,
        "flight_controller": setup.flight_controller,
        "onboard_estimator": setup.onboard_estimator,
        "command": setup.pilot.command,
        "lean_lag_s": setup.pilot.lean_lag_s,
        "gyro_blend_s": setup.pilot.gyro_blend_s if setup.pilot.lean_lag_s > 0 else None,
        "stamps": setup.stamps,
        "contact_mode": setup.contact_mode,
        "duration_s": setup.duration_s,
        "hover_s": setup.hover_s,
        "faults": list(setup.faults),
        "fps": setup.fps,
        "latency_ms": _latency_ms(setup),
        "latency_range_ms": [round(v * 1000.0, 3) for v in setup.latency_range_s],
        "latency_label": f"{setup.latency_label} ms",
        "by_estimator": by_estimator,
        "cells": cells,
        "fault_outcomes": fault_outcomes(records) if setup.faults else {},
        "setup": setup_description(setup),
    }


def _ending(record: RunRecord) -> str:
    """How a run with a fault ended: ``perched``, ``landed`` (the pilot sensed the
    touchdown), ``motors stopped in the air`` (the vehicle's own watchdog, or a stop above
    ``FALL_M``), or what stopped the run otherwise (its reason: the motors still on)."""
    if record.success:
        return "perched"
    height = record.motor_stop_height_m
    if math.isfinite(height):
        return "landed" if height <= FALL_M else "motors stopped in the air"
    return record.reason


def fault_outcomes(records: list[RunRecord]) -> dict[str, object]:
    """Per fault injected: runs, how they ended, motor stops above ``FALL_M``, and the
    longest time the vehicle went without a setpoint while the pilot flew it."""
    out: dict[str, object] = {}
    for kind in sorted({r.fault for r in records if r.fault}):
        rs = [r for r in records if r.fault == kind]
        endings = dict(Counter(_ending(r) for r in rs))
        gaps = [r.max_setpoint_gap_s for r in rs if math.isfinite(r.max_setpoint_gap_s)]
        out[kind] = {
            "runs": len(rs),
            "ended": endings,
            "motor_stops_above_5cm": sum(
                math.isfinite(r.motor_stop_height_m) and r.motor_stop_height_m > FALL_M for r in rs
            ),
            "max_setpoint_gap_s": max(gaps) if gaps else math.nan,
        }
    return out


def _num(v: object, fmt: str = ".1f") -> str:
    return format(v, fmt) if isinstance(v, float) and math.isfinite(v) else "-"


def markdown(records: list[RunRecord]) -> str:
    """``perch.md``: one row per wind and estimator."""
    lines = [
        "| wind | mean / gust (m/s) | estimator | latency (ms) | runs | perched | 95 % interval | "
        "offset p50 / p95 (mm) | speed max (m/s) | time offset after 3 s: error p95 (ms), "
        "within 10 ms | failures |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for (wind, estimator, latency), rs in group(records).items():
        s = summarise(rs)
        low, high = s.success_interval
        fails = (
            ", ".join(f"{k} {v}" for k, v in sorted(s.reasons.items()) if k != "perched") or "none"
        )
        clock = time_offset_summary(rs)
        errors = clock["error_ms"]
        assert isinstance(errors, dict)
        lines.append(
            f"| {wind} | {rs[0].wind_mean_mps:g} / {rs[0].turbulence_sigma_mps:g} | "
            f"{estimator} | {latency} | {s.runs} | {s.success_rate:.1%} | {low:.1%} - {high:.1%} | "
            f"{_num(s.contact_offset_mm['p50'])} / {_num(s.contact_offset_mm['p95'])} | "
            f"{_num(s.contact_speed_mps['max'], '.2f')} | "
            f"{_num(errors['p95'])}, {clock['within_goal']} of {clock['runs_with_estimate']} | "
            f"{fails} |"
        )
    return "\n".join(lines) + "\n"


def write_reports(
    log: CampaignLog,
    setup: PerchSetup,
    trajectories: list[PerchResult],
    keys: set[RunKey] | None = None,
) -> dict[str, object]:
    """``perch.json``, ``perch.md``, ``trajectories.png`` and, with several winds,
    ``wind.png`` (with several latencies ``latency.png``) beside ``runs.csv``; returns the
    JSON content. ``keys``: the runs the reports cover (default every row of the log; a
    resumed campaign's file may hold rows of other seeds or cells)."""
    out = log.out
    records = log.records if keys is None else [r for r in log.records if r.key in keys]
    content = summary_json(records, setup)
    (out / "perch.json").write_text(json.dumps(content, indent=2, default=str), encoding="utf-8")
    (out / "perch.md").write_text(markdown(records), encoding="utf-8")
    if trajectories:
        perch_figure(
            str(out / "trajectories.png"),
            [
                (f"{r.estimator} seed {r.seed} ({r.reason})", r.t_s, r.p_magnet_m, r.stage)
                for r in trajectories[:5]
            ],
            setup.plate_z_m,
            CONTACT_RADIUS_MM,
        )
    groups = group(records)
    if len({w for w, _, _ in groups}) > 1:
        by_wind = _series(groups, lambda rs: rs[0].wind_mean_mps)
        sweep_figure(str(out / "wind.png"), by_wind, wilson_interval, REASONS[1:])
    if len({lat for _, _, lat in groups}) > 1:
        by_latency = _series(groups, lambda rs: float(rs[0].latency_set_ms.split("-")[0]))
        sweep_figure(
            str(out / "latency.png"),
            by_latency,
            wilson_interval,
            REASONS[1:],
            x_label="camera latency (ms)",
            unit="ms",
        )
    return content


def _series(
    groups: dict[Cell, list[RunRecord]], x: Callable[[list[RunRecord]], float]
) -> dict[str, list[tuple[float, int, int, dict[str, int]]]]:
    """Per estimator, each cell's (x, successes, runs, failures by cause)."""
    series: dict[str, list[tuple[float, int, int, dict[str, int]]]] = {}
    for (_, estimator, _), rs in groups.items():
        wins = sum(r.success for r in rs)
        reasons = dict(Counter(r.reason for r in rs if not r.success))
        series.setdefault(estimator, []).append((x(rs), wins, len(rs), reasons))
    return series

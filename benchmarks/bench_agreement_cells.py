"""Perching cells flown by the model's onboard loops and by the Crazyflie firmware's PID, on
the same seeds in each wind (issue: the model against the firmware, side by side).

    .venv/bin/python benchmarks/bench_agreement_cells.py [--runs 200] [--seed 1300000]
        [--winds none,light,moderate,strong] [--workers 2] [--stock-gain]
        [--estimator truth] [--onboard-estimator model] [--command velocity]

Each cell is ``perchpose perch --estimator E --onboard-estimator O --command C --wind W
[--flight-controller crazyflie-pid]`` (realistic senses, live stamps, disturbances on: the
defaults), so the vehicle's loops alone differ. The defaults fly the true pose on the model's
onboard estimate, which keeps the camera pipeline and the onboard filter out of it; the goal
cells (``--estimator covariance --onboard-estimator crazyflie-kalman --command attitude``) put
the firmware's Kalman filter under both. Both vehicles fly the velocity gain the pilot sets at
its take-over (6 /s: ``velCtlPid.vxKp`` 35 on the firmware, written where its parameter system
writes it); ``--stock-gain`` adds a row for each at the vehicle's own gain (the firmware's
25 deg per m/s, about 4.3 /s). Prints a table with 95 % Wilson intervals and, per wind, the
seeds that perched on one vehicle only. Needs ``cffirmware``
(``../shared/firmware/install-cffirmware``).
"""

from __future__ import annotations

import argparse
import collections
from dataclasses import dataclass, replace

from perchpose.app.inputs import load_camera
from perchpose.app.perch import PerchCampaign
from perchpose.evaluation.perching import wilson_interval
from perchpose.sim.campaign import run_campaign

ROWS = (
    ("model", "model", True),
    ("firmware PID", "crazyflie-pid", True),
)
STOCK_ROWS = (
    ("model, stock gain", "model", False),
    ("firmware PID, stock gain", "crazyflie-pid", False),
)


@dataclass(frozen=True)
class Cell:
    """What every row of a wind shares: the pose estimator, the onboard estimator, the command."""

    estimator: str
    onboard_estimator: str
    command: str
    runs: int
    seed: int
    workers: int


def fly(cell: Cell, wind: str, flight_controller: str, pilot_gain: bool) -> dict[int, str]:
    """Each seed's outcome: ``perched`` or the failure's reason."""
    campaign = PerchCampaign.from_options(
        load_camera("preset:fpv"),
        estimators=cell.estimator,
        runs=cell.runs,
        seed=cell.seed,
        wind=wind,
        flight_controller=flight_controller,
        onboard_estimator=cell.onboard_estimator,
        command=cell.command,
    )
    (setup,) = campaign.setups
    if not pilot_gain:
        setup = replace(setup, pilot=replace(setup.pilot, velocity_gain_per_s=None))
    results = run_campaign(setup, cell.runs, cell.seed, workers=cell.workers)
    return {r.seed: "perched" if r.success else r.reason for r in results}


def row(wind: str, label: str, outcomes: dict[int, str]) -> str:
    """One table row: the rate, its 95 % Wilson interval and the failures by reason."""
    runs = len(outcomes)
    perched = sum(outcome == "perched" for outcome in outcomes.values())
    failures = collections.Counter(o for o in outcomes.values() if o != "perched")
    low, high = wilson_interval(perched, runs)
    causes = ", ".join(f"{k} {v}" for k, v in failures.most_common()) or "none"
    return (
        f"| {wind} | {label} | {100 * perched / runs:.1f} % | "
        f"{100 * low:.1f}-{100 * high:.1f} | {causes} |"
    )


def only_on(first: dict[int, str], second: dict[int, str]) -> list[int]:
    """The seeds that perched on the first vehicle and not on the second."""
    return sorted(s for s, o in first.items() if o == "perched" and second.get(s) != "perched")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=200)
    parser.add_argument("--seed", type=int, default=1300000)
    parser.add_argument("--winds", default="none,light,moderate,strong")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--stock-gain", action="store_true", help="also fly the stock gain")
    parser.add_argument("--estimator", default="truth")
    parser.add_argument("--onboard-estimator", default="model")
    parser.add_argument("--command", default="velocity")
    args = parser.parse_args()
    cell = Cell(
        args.estimator, args.onboard_estimator, args.command, args.runs, args.seed, args.workers
    )
    rows = ROWS + STOCK_ROWS if args.stock_gain else ROWS
    print(f"| wind | vehicle | perched of {args.runs} | 95 % interval | failures |")
    print("|---|---|---|---|---|")
    paired: list[str] = []
    for wind in args.winds.split(","):
        flown: list[dict[int, str]] = []
        for label, controller, gain in rows:
            flown.append(fly(cell, wind, controller, gain))
            print(row(wind, label, flown[-1]), flush=True)
        model, firmware = flown[0], flown[1]
        paired.append(
            f"{wind}: perched only on the model {only_on(model, firmware)}, "
            f"only on the firmware {only_on(firmware, model)}"
        )
    print("\n".join(paired))


if __name__ == "__main__":
    main()

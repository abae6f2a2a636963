"""Perching cells flown by the model's onboard loops and by the Crazyflie firmware's PID, on
the same seeds in each wind (issue: the model against the firmware, side by side).

    .venv/bin/python benchmarks/bench_agreement_cells.py [--runs 200] [--seed 1300000]
        [--winds none,light,moderate,strong] [--workers 2] [--stock-gain]

Each cell is ``perchpose perch --estimator truth --wind W [--flight-controller crazyflie-pid]``
(realistic senses, live stamps, disturbances on: the defaults), so the vehicle alone differs;
the true pose keeps the camera pipeline out of it. Both vehicles fly the velocity gain the
pilot sets at its take-over (6 /s: ``velCtlPid.vxKp`` 35 on the firmware, written where its
parameter system writes it); ``--stock-gain`` adds a row for each at the vehicle's own gain
(the firmware's 25 deg per m/s, about 4.3 /s). Prints a table with 95 % Wilson intervals.
Needs ``cffirmware`` (``../shared/firmware/install-cffirmware``).
"""

from __future__ import annotations

import argparse
import collections
from dataclasses import replace

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


def cell(
    wind: str, flight_controller: str, pilot_gain: bool, runs: int, seed: int, workers: int
) -> tuple[int, collections.Counter[str]]:
    camera = load_camera("preset:fpv")
    campaign = PerchCampaign.from_options(
        camera,
        estimators="truth",
        runs=runs,
        seed=seed,
        wind=wind,
        flight_controller=flight_controller,
    )
    (setup,) = campaign.setups
    if not pilot_gain:
        setup = replace(setup, pilot=replace(setup.pilot, velocity_gain_per_s=None))
    results = run_campaign(setup, runs, seed, workers=workers)
    failures = collections.Counter(r.reason for r in results if not r.success)
    return sum(r.success for r in results), failures


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=200)
    parser.add_argument("--seed", type=int, default=1300000)
    parser.add_argument("--winds", default="none,light,moderate,strong")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--stock-gain", action="store_true", help="also fly the stock gain")
    args = parser.parse_args()
    rows = ROWS + STOCK_ROWS if args.stock_gain else ROWS
    print(f"| wind | vehicle | perched of {args.runs} | 95 % interval | failures |")
    print("|---|---|---|---|---|")
    for wind in args.winds.split(","):
        for label, controller, gain in rows:
            perched, failures = cell(wind, controller, gain, args.runs, args.seed, args.workers)
            low, high = wilson_interval(perched, args.runs)
            causes = ", ".join(f"{k} {v}" for k, v in failures.most_common()) or "none"
            print(
                f"| {wind} | {label} | {100 * perched / args.runs:.1f} % | "
                f"{100 * low:.1f}-{100 * high:.1f} | {causes} |",
                flush=True,
            )


if __name__ == "__main__":
    main()

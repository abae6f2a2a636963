"""How the perching rate falls as a flow deck's odometry gets noisier.

    .venv/bin/python benchmarks/bench_flow_deck.py [--runs 60] [--seed 600000] [--workers 2]
        [--wind moderate] [--estimator truth] [--pixel-noise 0 0.01 0.02 0.04 0.08]

Each line flies ``--runs`` runs of ``perchpose perch`` with realistic senses (live stamps) and
the flow deck's odometry (``sim.flow_deck``) at one pixel noise per flow sample, every other
part of the flow deck's error as drawn by default, and says the share perched (Wilson 95 %
interval) and how the others failed; the first line is the white odometry the campaigns fly
by default. The estimator defaults to ``truth`` (the target's true pose, stamped and late as a
measured one would be) so that the odometry alone is compared.
"""

from __future__ import annotations

import argparse
from collections import Counter
from dataclasses import replace

from perchpose.app.inputs import load_camera
from perchpose.app.perch import PerchCampaign
from perchpose.evaluation.perching import wilson_interval
from perchpose.sim.campaign import run_campaign
from perchpose.sim.flow_deck import FlowDeck
from perchpose.sim.perch import PerchSetup


def cell(setup: PerchSetup, runs: int, seed: int, workers: int) -> tuple[int, Counter[str]]:
    reasons = Counter(r.reason for r in run_campaign(setup, runs, seed, workers))
    return reasons["perched"], reasons


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=60)
    parser.add_argument("--seed", type=int, default=600000)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--wind", default="moderate")
    parser.add_argument("--estimator", default="truth")
    parser.add_argument(
        "--pixel-noise", type=float, nargs="+", default=[0.0, 0.01, 0.02, 0.04, 0.08]
    )
    args = parser.parse_args()
    camera = load_camera("preset:fpv")

    def setup_for(odometry: str) -> PerchSetup:
        campaign = PerchCampaign.from_options(
            camera, estimators=args.estimator, runs=args.runs, wind=args.wind, odometry=odometry
        )
        return campaign.setups[0]

    cells = [("white", setup_for("white"))]
    flow = setup_for("flow-deck")
    for px in args.pixel_noise:
        deck = FlowDeck(pixel_noise_px=px)
        cells.append(
            (f"flow deck {px:g} px", replace(flow, sensing=replace(flow.sensing, flow_deck=deck)))
        )
    print(
        f"{args.runs} runs per line, seeds {args.seed}-{args.seed + args.runs - 1}, "
        f"{args.wind} wind, estimator {args.estimator}, live stamps"
    )
    for name, setup in cells:
        perched, reasons = cell(setup, args.runs, args.seed, args.workers)
        low, high = wilson_interval(perched, args.runs)
        others = ", ".join(f"{r} {n}" for r, n in reasons.most_common() if r != "perched")
        print(
            f"{name:<20} {100 * perched / args.runs:5.1f} % ({100 * low:.1f}-{100 * high:.1f})"
            f"  {others}",
            flush=True,
        )


if __name__ == "__main__":
    main()

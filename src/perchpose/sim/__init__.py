"""Simulation: a renderer of the target through a camera model, and scenarios with ground truth."""

from perchpose.sim.render import ImageQuality, Renderer
from perchpose.sim.scenarios import Scenario, approach, static_grid

__all__ = ["ImageQuality", "Renderer", "Scenario", "approach", "static_grid"]

"""Inputs and outputs at the edge of the library: frame sources, pose sinks, overlay video."""

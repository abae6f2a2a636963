"""Corners fitted to the image from a found quad: the method chosen per marker (``refinement``),
the fit of the four border edges through the lens model (``edge_fit``, its compiled points,
profiles and lines in ``edge_geometry``, the blurred-step model in ``step_model``) and the fit of
a small marker's whole printed pattern (``pattern_fit``, its model in ``pattern_model``)."""

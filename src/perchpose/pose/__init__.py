"""Poses from corners: each marker's own (IPPE, ``marker``), every marker's corners in one
least-squares fit with its covariance (``joint``), and the compiled refinement both share
(``refine``)."""

"""Fusion of the markers into one target pose: two strategies behind one interface
(``base.Fusion``): the paper's stages and sigma weights (``paper``), and the joint pose of every
marker's corners through a filter of its own (``covariance``); the covariance carried between
parametrisations (``transport``); whether a frame's markers agree (``consistency``)."""

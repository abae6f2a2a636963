"""The Kalman filters: the equations once, the paper's per-marker filter and the covariance
filter on the joint pose (``kalman``), and their matrix arithmetic, compiled (``steps``)."""

"""The standard normal distribution's CDF and density together, compiled (the edge and pattern
models integrate a Gaussian blur over each pixel with it)."""

from __future__ import annotations

import math

from perchpose.numeric.jit import compiled

_SQRT2 = math.sqrt(2.0)
_INV_SQRT_2PI = 1.0 / math.sqrt(2.0 * math.pi)
# Abramowitz and Stegun 7.1.26: erf to 1.5e-7
_ERF_P = 0.3275911
_ERF_A1, _ERF_A2, _ERF_A3, _ERF_A4, _ERF_A5 = (
    0.254829592,
    -0.284496736,
    1.421413741,
    -1.453152027,
    1.061405429,
)


@compiled
def normal_cdf_pdf_at(u: float) -> tuple[float, float]:
    """Standard normal CDF and density at ``u`` (the CDF via Abramowitz and Stegun 7.1.26,
    which shares its exponential with the density)."""
    z = abs(u) * (1.0 / _SQRT2)
    t = 1.0 / (1.0 + _ERF_P * z)
    gauss = math.exp(-z * z)
    erf = 1.0 - t * (_ERF_A1 + t * (_ERF_A2 + t * (_ERF_A3 + t * (_ERF_A4 + t * _ERF_A5)))) * gauss
    return 0.5 + 0.5 * math.copysign(erf, u), gauss * _INV_SQRT_2PI

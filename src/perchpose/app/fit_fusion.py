"""``perchpose fit-fusion``: the paper fusion's sigmas fitted to labelled data."""

from __future__ import annotations

from dataclasses import dataclass

from perchpose.errors import PerchposeError
from perchpose.evaluation.experiments import FusionFit, FusionSamples


@dataclass(frozen=True)
class FitFusionOptions:
    """The labelled data (columns true_* and each marker's m0_* / m1_*, or a track file with
    ``truth_file``), and where to write the fitted weights as JSON (None: nowhere)."""

    data: str
    truth_file: str | None = None
    json_out: str | None = None


@dataclass(frozen=True)
class FusionFitted:
    """Both fits and the samples they came from."""

    fit: FusionFit
    samples: FusionSamples


def run(options: FitFusionOptions) -> FusionFitted:
    """Fit the sigmas by least squares and by the paper's LMS; write the JSON where asked."""
    from perchpose.evaluation.experiments import fit_fusion
    from perchpose.evaluation.fusion_data import load_fusion_samples, write_fusion_fit

    samples = load_fusion_samples(options.data, options.truth_file)
    try:
        fit = fit_fusion(samples)
    except ValueError as exc:
        raise PerchposeError(f"{options.data}: {exc}") from exc
    if options.json_out:
        write_fusion_fit(options.json_out, fit)
    return FusionFitted(fit, samples)

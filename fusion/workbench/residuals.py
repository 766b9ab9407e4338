"""The model against the recording: a fit of the model with the recording's encoder zeros
(:func:`fit_model`), its χ² and residual RMS over the noise floor, the fit problem at a
fit's estimates (:func:`problem_at`, with candidate effects appended at zero), and each
sensor axis's residual against its noise (:class:`AxisFit`, the fit in % as MATLAB's
``compare``)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from armfusion.fusion.identification.data import FitData, with_encoder_zeros
from armfusion.fusion.identification.identify import identify
from armfusion.fusion.identification.problem import FitProblem
from armfusion.fusion.identification.result import Identification
from armfusion.fusion.identification.settings import IdentifySettings
from armfusion.fusion.workbench.gauges import held_elements, structural_gauges
from armfusion.models.effects import Effect, Model


@dataclass(frozen=True)
class AxisFit:
    """One sensor axis: residual RMS against the noise floor (physical units, window
    means) and the fit in % (NRMSE)."""

    stream: str
    axis: str
    unit: str
    rms: float
    noise: float
    fit_percent: float | None
    """None where the axis does not vary beyond 3× its noise (nothing to fit)."""
    autocorr1: float = 0.0
    """Lag-1 autocorrelation of the residual (whiteness): for white noise about ``±1/√n``;
    a missing effect makes it near 1."""

    @property
    def ratio(self) -> float:
        return self.rms / self.noise if self.noise > 0 else np.inf


def chi2_total(res: Identification) -> float:
    """Σ r² of a fit's data residuals (noise-weighted)."""
    dof = max(res.n_residuals - int((~res.held).sum()), 1)
    return float(res.chi2_red * dof)


def rms_ratio_of(res: Identification) -> float:
    """The whole model's residual RMS over its noise floor."""
    return float(np.sqrt(chi2_total(res) / max(res.n_residuals, 1)))


def fit_model(model: Model, data: FitData, streams: Sequence[str] | None = None,
              settings: IdentifySettings | None = None,
              attitude0_rad: np.ndarray | None = None, progress=None,
              hold: Sequence[str] = ()) -> Identification:
    """``identify`` with the recording's encoder zeros added to ``model``, its structural gauges
    held (a mount rotation about its own joint's axis where that is the joint's zero:
    :func:`armfusion.fusion.workbench.gauges.structural_gauges`) and ``hold`` (elements or blocks) at
    their priors."""
    hold = [*hold, *held_elements(structural_gauges(model, data))]
    return identify(with_encoder_zeros(model), data, streams, settings, hold=hold,
                    attitude0_rad=attitude0_rad, progress=progress)


def problem_at(fit: Identification, data: FitData, extra: Sequence[Effect], streams: Sequence[str],
             settings: IdentifySettings) -> tuple[FitProblem, np.ndarray]:
    base = fit.model.with_values(fit.model_x)
    big = base.with_effects(extra) if extra else base
    att = fit.attitude_rad if fit.attitude_rad is not None else np.zeros(3)
    pb = FitProblem(big, data, streams, settings.estimate_attitude, att, encoder_scale=settings.encoder_scale)
    return pb, pb.x0.copy()


def axis_fits(R: np.ndarray, data: FitData, streams: Sequence[str], model: Model) -> list[AxisFit]:
    """Per sensor axis from the noise-weighted residuals ``R (N, axes)`` (streams in order)."""
    sm = model.stream_models()
    out = []
    i = 0
    for s in streams:
        y = data.counts[s]
        g = np.abs(sm[s].gain)
        sig = np.broadcast_to(data.sigma_counts[s], (y.shape[1],))
        for k in range(y.shape[1]):
            e = R[:, i] * sig[k]  # counts
            i += 1
            spread = np.linalg.norm(y[:, k] - y[:, k].mean())
            # an axis that does not vary beyond its noise has no fit % (MATLAB's would be ~0)
            varies = np.std(y[:, k]) > 3.0 * sig[k]
            fit = 100.0 * (1.0 - np.linalg.norm(e) / spread) if varies else None
            # not centred: an offset is colour too (white residuals have mean zero)
            ac = float(e[1:] @ e[:-1] / max(e @ e, 1e-300)) if len(e) > 2 else 0.0
            out.append(AxisFit(s, sm[s].channels[k], sm[s].unit, float(np.sqrt(np.mean(e**2)) / g[k]),
                               float(sig[k] / g[k]), None if fit is None else float(fit), ac))
    return out

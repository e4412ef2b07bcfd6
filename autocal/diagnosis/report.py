"""The diagnosis's result and its products: diagnosis.json, summary.txt and plots.

:class:`Diagnosis` is what a search (:func:`autocal.diagnosis.stepwise.diagnose`) finds;
:func:`write_diagnosis` writes it (:func:`summary_text` is the human-readable summary).
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from autocal.core.observation import Observation
from autocal.diagnosis.extended_fit import ExtendedFit
from autocal.diagnosis.impact import (
    FORWARD_MODEL_ACCURACY,
    NEGLIGIBLE_G_FRACTION,
    NEGLIGIBLE_TRXR_K,
)
from autocal.diagnosis.normal_equations import IDENTIFIABLE_RESOLUTION, MIN_IDENTIFIABLE
from autocal.plots import plot_gain_series, plot_residuals, run_title, waterfall_antennas

logger = logging.getLogger(__name__)


@dataclass
class Diagnosis:
    """Result of :func:`~autocal.diagnosis.stepwise.diagnose`.

    Attributes
    ----------
    steps
        One dict per accepted step: ``name``, ``parameters`` ``{p: {value, sigma}}``,
        ``statistic`` (Delta BIC), ``delta`` (Delta chi^2), ``gap_before``,
        ``gap_after``, ``candidates`` (every candidate's Delta BIC).
    effects
        Names of the accepted effects, in order.
    initial_gap, final_gap
        Gap metrics of the starting and final models.
    identifiability
        ``{effect: fraction of Fisher information not absorbed by (G, n)}`` at the start
        (0: below :data:`~autocal.diagnosis.normal_equations.IDENTIFIABLE_RESOLUTION`,
        degenerate with ``(G, n)``).
    config
        Statistic, threshold, prior and settings.
    residual_snapshots
        ``[(label, (a, Npol, Ntime, Nfreq) normalised residuals)]`` of the antenna-pols the
        residual plots show (:func:`residual_snapshot`: the first antennas, every pol).
    product_change
        How the calibration products change from the starting model to the diagnosed one
        (:func:`~autocal.diagnosis.impact.product_impact`); each step has its own under
        ``product_impact``.
    unexplained
        ``None`` when the final model fits to within the noise; else what remains and its
        structure (:func:`~autocal.diagnosis.gap.describe_unexplained`): no catalogue entry
        explains it.
    negligible
        Effects detected (significant by the same test, kept in the fitted model) whose
        impact on ``G`` and ``Trxr`` is negligible
        (:func:`~autocal.diagnosis.impact.is_negligible`): reported as "detected,
        negligible", not named among :attr:`effects`; their steps say ``negligible: true``.
    absorbed
        Effects that passed the test but are negligible for the products and explain less
        than :data:`~autocal.diagnosis.gap.ABSORBED_SHARE` of what the final model leaves
        unexplained (its excess chi^2): structure of that remainder a template happens to
        follow, not evidence of the effect (a clean day through an independently evaluated
        HERA beam, chi^2/dof 1.22, had a gain drift, a noise drift and a timing offset
        "detected" at 2 % of the remainder's excess each). Kept in the fit; listed under
        ``unexplained["absorbed"]`` with their shares; neither named nor "detected".
    below_model_accuracy
        Effects seen through the data's structure that passed the test and whose signal is
        below the forward model's accuracy for the model beam
        (:func:`~autocal.diagnosis.impact.forward_model_accuracy`, in
        ``config["forward_model_accuracy"]``) of the data rms (the step's ``signal_rms``):
        what autocal's own Tsky can be off by, which such a template fits
        as well as any instrument effect (clean days from an independent simulator had a
        gain drift "detected" at 3.6e-5-5.7e-5), whatever it would change in the products
        (the summary says "would move the products" of those that would). Kept in the fit;
        neither named nor "detected".
    indistinguishable
        ``None``, or the step at which the search stopped because an entry of the other
        domain (receiver against forward model, :func:`~autocal.diagnosis.rivals.domain`)
        that passes the same tests explains the residual about as well as the best
        (``Delta BIC`` within :data:`~autocal.diagnosis.rivals.DECISIVE_MARGIN`, or within
        :data:`~autocal.diagnosis.rivals.LEAD_SIGMAS` times the noise of the lead,
        ``lead_sigma``): the candidates
        with their statistics, what each would change in the products, and a message
        (:func:`~autocal.diagnosis.rivals.indistinguishable_record`). None of them is
        named (half an hour through an independently evaluated HERA beam left a linear
        trend that a noise drift, a clock offset and a missing CMB explained within
        Delta BIC 3.6 of each other).
    not_tested
        ``{entry: why}``: catalogue entries the search did not test at all on these data
        (e.g. the per-antenna entries above
        :data:`~autocal.diagnosis.feeds.FEED_JITTER_MAX_FEEDS` antenna-pols), so that their
        absence from :attr:`effects` is not read as "not present".
    rfi_flagging
        The band edges and RFI flagged from the autos before the first fit, as a
        calibration flags them (:func:`autocal.pipeline.flagging.flag_observation`;
        :func:`autocal.diagnosis.run.run_diagnosis` sets it): the calibration summary's
        ``rfi_flagging`` block, counts per reason or why nothing was flagged. ``None``:
        the caller did not flag (:func:`~autocal.diagnosis.stepwise.diagnose` on an
        observation). The outliers of the residual rounds are in
        ``config["outlier_flagging"]``.
    """

    steps: list[dict[str, Any]] = field(default_factory=list)
    effects: list[str] = field(default_factory=list)
    initial_gap: dict[str, Any] = field(default_factory=dict)
    final_gap: dict[str, Any] = field(default_factory=dict)
    identifiability: dict[str, float] = field(default_factory=dict)
    config: dict[str, Any] = field(default_factory=dict)
    residual_snapshots: list[tuple[str, np.ndarray]] = field(default_factory=list, repr=False)
    final_fit: ExtendedFit | None = field(default=None, repr=False)
    final_parameters: dict[str, dict[str, Any]] = field(default_factory=dict)
    product_change: dict[str, Any] = field(default_factory=dict)
    unexplained: dict[str, Any] | None = None
    negligible: list[str] = field(default_factory=list)
    absorbed: list[str] = field(default_factory=list)
    below_model_accuracy: list[str] = field(default_factory=list)
    indistinguishable: dict[str, Any] | None = None
    not_tested: dict[str, str] = field(default_factory=dict)
    rfi_flagging: dict[str, Any] | None = None

    def to_dict(self) -> dict[str, Any]:
        """JSON-serialisable form (without residual arrays)."""
        return {
            "effects": self.effects,
            "negligible": self.negligible,
            "absorbed": self.absorbed,
            "below_model_accuracy": self.below_model_accuracy,
            "indistinguishable": self.indistinguishable,
            "not_tested": self.not_tested,
            "rfi_flagging": self.rfi_flagging,
            "unexplained": self.unexplained,
            "steps": self.steps,
            "initial_gap": self.initial_gap,
            "final_gap": self.final_gap,
            "identifiability": self.identifiability,
            "final_parameters": self.final_parameters,
            "product_change": self.product_change,
            "config": self.config,
        }


def _jsonable(obj: Any) -> Any:
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _jsonable(obj.tolist())
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


def summary_text(diag: Diagnosis) -> str:
    """Human-readable summary of a diagnosis."""
    g0 = diag.initial_gap
    lines = [
        "autocal diagnose",
        f"statistic: {diag.config.get('statistic')}",
        f"threshold: Delta BIC > {diag.config.get('bic_threshold')} and "
        f"p < {diag.config.get('alpha')}",
        f"initial gap: chi2/dof = {g0.get('reduced_chi2', float('nan')):.4f}, "
        f"rms residual = {g0.get('rms_normalised_residual', float('nan')):.3f}",
        *_flagging_lines(diag),
        "",
    ]
    if not diag.steps and not diag.unexplained and not diag.indistinguishable:
        lines.append("no significant effect found: the model is consistent with the data")
    elif not diag.steps and not diag.indistinguishable:
        lines.append("no catalogue entry explains the gap (see 'unexplained' below)")
    for i, st in enumerate(diag.steps, 1):
        pars = ", ".join(
            f"{k} = {v['value']:.5g} +- {v['sigma']:.2g}" for k, v in st["parameters"].items()
        )
        marks = " [negligible]" if st.get("negligible") else ""
        if "absorbed_by_unexplained" in st:
            marks = " [negligible; part of the unexplained remainder]"
        if st.get("below_model_accuracy"):
            marks = (
                f" [{'negligible; ' if st.get('negligible') else ''}"
                f"{st['signal_rms']:.1e} of the data rms, below the forward model's accuracy]"
            )
        if st.get("superseded_by"):
            marks += f" [superseded by {st['superseded_by']}]"
        if st.get("dropped_in_backward_pass"):
            marks += f" [dropped at {st['dropped_in_backward_pass'].get('at', 'a re-test')}]"
        lines.append(
            f"step {i}: {st['name']}{marks} ({pars}); "
            f"Delta BIC = {st['statistic']:.1f}, "
            f"Delta chi2 = {st['delta']:.1f}; chi2/dof {st['gap_before']['reduced_chi2']:.4f} "
            f"-> {st['gap_after']['reduced_chi2']:.4f}"
        )
        if st.get("close_alternatives"):
            lines.append(
                "  nearly as good (Delta BIC within "
                f"{diag.config.get('decisive_margin')} of it, or within "
                f"{diag.config.get('lead_sigmas')} sigma of the noise of its "
                "lead; the same domain): "
                + ", ".join(f"{n} ({v:.1f})" for n, v in st["close_alternatives"].items())
            )
        if st.get("product_impact"):
            lines.append("  " + _impact_text(st["product_impact"]))
    if diag.negligible:
        lines.append(
            "detected, negligible for the calibration products (kept in the fit, not named): "
            + ", ".join(diag.negligible)
        )
    if diag.absorbed and diag.unexplained:
        shares = {a["name"]: a["share"] for a in diag.unexplained.get("absorbed", [])}
        lines.append(
            "fitted, but part of the unexplained remainder rather than evidence of the effect "
            "(each explains little of its excess chi2; negligible for the products): "
            + ", ".join(f"{n} ({100 * shares.get(n, float('nan')):.1f} %)" for n in diag.absorbed)
        )
    if diag.below_model_accuracy:
        lines.append(
            "fitted, but below the forward model's accuracy (a signal under "
            f"{diag.config.get('forward_model_accuracy', FORWARD_MODEL_ACCURACY):g} of the "
            "data rms, which autocal's own Tsky can be off "
            "by; not attributed, neither to the instrument nor to the model): "
            + ", ".join(
                name + ("" if _negligible_step(diag, name) else " (would move the products)")
                for name in diag.below_model_accuracy
            )
        )
    if diag.indistinguishable:
        lines.append(diag.indistinguishable["message"])
    for name, why in diag.not_tested.items():
        lines.append(f"not tested: {name} ({why})")
    rej = diag.config.get("last_rejected")
    if rej:
        lines.append(
            f"best remaining candidate {rej['name']}: Delta BIC = {rej['statistic']:.1f} "
            f"({rej.get('reason') or 'not significant'})"
        )
    lines.append("")
    lines.append("not identifiable from these data (Fisher fraction after (G, n) projection):")
    for name, frac in sorted(diag.identifiability.items()):
        if frac < MIN_IDENTIFIABLE:
            shown = f"{frac:.2e}" if frac > 0 else f"< {IDENTIFIABLE_RESOLUTION:.0e} (degenerate)"
            lines.append(f"  {name}: {shown}")
    fg = diag.final_gap
    lines.append(
        f"final gap: chi2/dof = {fg.get('reduced_chi2', float('nan')):.4f}, "
        f"rms residual = {fg.get('rms_normalised_residual', float('nan')):.3f}"
    )
    if diag.unexplained:
        lines.append(diag.unexplained["message"])
    if diag.steps and diag.product_change:
        lines.append("calibration products, starting model -> diagnosed model: ")
        lines.append("  " + _impact_text(diag.product_change))
    return "\n".join(lines) + "\n"


#: How summary.txt names the reasons of the flagging before the fit.
_REASON_TEXT = {
    "band_edge": "band edge",
    "rfi_frequency": "RFI in frequency",
    "rfi_time": "RFI in time",
    "no_data": "no usable data",
}


def _flagging_lines(diag: Diagnosis) -> list[str]:
    """Return the lines of summary.txt on what was flagged: before the fit, then as outliers."""
    lines = []
    rfi = diag.rfi_flagging
    if rfi is not None and not rfi.get("applied"):
        lines.append(f"flagged before the fit: nothing; {rfi.get('why', 'not applied')}")
    elif rfi is not None:
        fractions = rfi.get("fractions", {})
        shares = ", ".join(
            f"{text} {100 * fractions.get(reason, 0.0):.3g} %"
            for reason, text in _REASON_TEXT.items()
        )
        lines.append(
            f"flagged before the fit (band edges and RFI from the autos): "
            f"{rfi.get('band_edge_channels', 0)} band-edge channel(s), "
            f"{rfi.get('rfi_channels', 0)} RFI channel(s), "
            f"{rfi.get('rfi_integrations', 0)} RFI integration(s); samples: {shares}"
        )
    outliers = diag.config.get("outlier_flagging")
    if outliers and outliers.get("enabled"):
        lines.append(
            f"outliers flagged in the residuals: {outliers.get('samples_flagged', 0)} samples "
            f"in {outliers.get('rounds', 0)} round(s) "
            f"({outliers.get('threshold_sigma')} sigma of clean residuals' tails, "
            f"{outliers.get('threshold_robust_sigma', float('nan')):.1f} robust sigma of the "
            "high-passed residuals)"
        )
        noise = outliers.get("noise_like")
        if noise:
            lines.append(
                f"  then {noise['samples']} more (largest {noise['peak_sigma']:.1f} sigma), no "
                f"more than clean noise gives at that threshold (up to {noise['limit']}): left "
                "unflagged, not searched again"
            )
    return lines


def _negligible_step(diag: Diagnosis, name: str) -> bool:
    """Return whether the kept step of effect ``name`` was negligible for the products."""
    for st in reversed(diag.steps):
        if st["name"] == name and not st.get("dropped_in_backward_pass"):
            return bool(st.get("negligible"))
    return True


def _impact_text(impact: dict[str, Any]) -> str:
    """One line on how G and Trxr moved (see :func:`~autocal.diagnosis.impact.product_impact`)."""
    g, t = impact.get("G", {}), impact.get("Trxr", {})
    nan = float("nan")
    if "median_change_over_sigma" not in g:
        return "no channel to compare"
    verdict = "significant" if impact.get("significant") else "within the errors"
    return (
        f"G changes by {100 * g['median_relative_change']:+.2g} % (median; "
        f"{g['median_change_over_sigma']:.2g} total sigma, worst channel "
        f"{g['max_change_over_sigma']:.2g}); Trxr by {t.get('median_change_K', nan):+.3g} K "
        f"({t.get('median_change_over_sigma', nan):.2g} sigma, worst "
        f"{t.get('max_change_over_sigma', nan):.2g}): {verdict}" + _time_change_text(impact)
    )


def _time_change_text(impact: dict[str, Any]) -> str:
    """How the products' variation in time changed, when it did.

    See :func:`~autocal.diagnosis.impact.is_negligible`.
    """
    gt, tt = impact.get("G_time", {}), impact.get("Trxr_time", {})
    parts = []
    if gt.get("max_abs_relative_change", 0.0) >= NEGLIGIBLE_G_FRACTION:
        parts.append(
            f"G(t) {100 * gt['rms_relative_change']:.2g} % rms over time (largest "
            f"{100 * gt['max_abs_relative_change']:.2g} %)"
        )
    if tt.get("max_abs_change_K", 0.0) >= NEGLIGIBLE_TRXR_K:
        parts.append(
            f"Trxr(t) up to {tt['median_max_abs_change_K']:.3g} K (median channel; largest "
            f"{tt['max_abs_change_K']:.3g} K)"
        )
    return f"; in time: {', '.join(parts)}" if parts else ""


def residual_snapshot(fit: ExtendedFit) -> np.ndarray:
    """Return what the residual plots show of a fit: ``(a, Npol, Ntime, Nfreq)``.

    The normalised residuals of the first :func:`~autocal.plots.waterfall_antennas`
    antennas, every pol: the antenna-pols ``autocal calibrate``'s ``residuals.png`` shows
    (at most :data:`~autocal.plots.MAX_PLOTTED`).
    """
    return fit.residuals_of_first(waterfall_antennas(fit.G.shape[1]))


def _waterfall_labels(shape: tuple[int, ...], obs: Observation | None) -> list[str]:
    """Return ``ant <number> <pol>`` of each shown antenna-pol, antenna by antenna.

    Without ``obs``: ``antenna index <i>, pol index <j>``.
    """
    nant, npol = shape[:2]
    if obs is None:
        return [f"antenna index {a}, pol index {p}" for a in range(nant) for p in range(npol)]
    return [f"ant {a} {p}" for a in obs.antennas[:nant].tolist() for p in obs.pols]


def write_diagnosis(
    diag: Diagnosis,
    out_dir: str | Path,
    obs: Observation | None = None,
    *,
    stems: tuple[str, ...] = (),
) -> Path:
    """Write ``diagnosis.json``, ``summary.txt`` and plots.

    The plots: residual waterfalls before/after each step (``residuals_step<i>.png``, each
    antenna-pol's before and after side by side; ``residuals.png`` when no step was
    accepted), and ``gain_series.png`` (the per-integration gain series of ``gain_jitter`` /
    ``antenna_gain_jitter`` steps). The waterfalls are of every antenna-pol up to
    :data:`~autocal.plots.MAX_PLOTTED` (the first antennas with every pol, as ``autocal
    calibrate``'s ``residuals.png``; :func:`residual_snapshot`); each panel names its
    antenna and pol, the title the files, JD range and antennas, and with more antenna-pols
    the figure says 'showing N of M antenna-pols' (also logged).

    Parameters
    ----------
    diag
        The diagnosis.
    out_dir
        Output folder (created).
    obs
        The observation (axes of the residual plots); without it the plots use indices.
    stems
        Input file stems, named in the plots' titles.

    Returns
    -------
    Path
        The folder.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    (out / "diagnosis.json").write_text(json.dumps(_jsonable(diag.to_dict()), indent=2))
    (out / "summary.txt").write_text(summary_text(diag))
    snaps = [(label, np.asarray(res)) for label, res in diag.residual_snapshots]
    labels = _waterfall_labels(snaps[0][1].shape, obs) if snaps else []
    title, total = None, None
    if obs is not None:
        title = run_title(obs.jds, obs.antennas, obs.pols, stems)
        total = len(obs.antennas) * len(obs.pols)
    if total is not None and len(labels) < total:
        logger.info(
            "residual plots show %d of %d antenna-pols (%s)", len(labels), total, ", ".join(labels)
        )
    for i in range(1, len(snaps)):
        (before, res0), (after, res1) = snaps[i - 1], snaps[i]
        nt, nf = res1.shape[-2:]
        freqs = obs.freqs if obs is not None else np.arange(nf) * 1e6
        lsts = obs.lsts if obs is not None else np.arange(nt, dtype=float)
        # each antenna-pol's before and after side by side: (K, 2, Ntime, Nfreq)
        pairs = np.stack([res0.reshape(-1, nt, nf), res1.reshape(-1, nt, nf)], axis=1)
        plot_residuals(
            [f"{label}, {when}" for label in labels for when in (before, after)],
            pairs.reshape(-1, nt, nf),
            freqs,
            lsts,
            out / f"residuals_step{i}.png",
            title=f"{title}\nstep {i}: before and after" if title else f"step {i}",
            total=total,
            shown=len(labels),
            ncols=2,
        )
    if len(snaps) == 1 and obs is not None:
        first, res0 = snaps[0]
        plot_residuals([f"{label}, {first}" for label in labels],
                       res0.reshape(-1, *res0.shape[-2:]), obs.freqs, obs.lsts,
                       out / "residuals.png", title=title, total=total)  # fmt: skip
    plot_gain_series(diag.steps, out / "gain_series.png", title=title)
    logger.info("wrote diagnosis to %s", out)
    return out

"""``torchsvs track --estimator auto``: fit the candidates without truth, keep the best.

Each candidate (:data:`CANDIDATES`) is completed from the data (:func:`~torchsvs.fitting.defaults.
complete_settings`, the noise read once and shared), tuned by SURE on windows of the sample
(:func:`~torchsvs.fitting.tuning.self_tune`), then run on the whole sample, where Stein's
unbiased risk estimate (:mod:`torchsvs.accuracy`) scores its position error. The candidate of
the lowest estimated error (penalised by its relative uncertainty, :data:`CAUTION`) wins; its
settings are what ``track`` then runs on the file. The candidates' table is printed and
written to the run's JSON summary.

The estimate each candidate is chosen by is unbiased for its error at fixed settings; its fit
on the same tracks and choosing the least of a few add optimism, which :func:`compared` holds
against a challenger (what its fit learned, the probes' spread, the noise reading's range).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field, replace
from typing import Any

import numpy as np
import torch

from torchsvs.accuracy import RiskTerms
from torchsvs.datasets import RecordedTracks
from torchsvs.fitting.defaults import (
    GUARD_ERRORS,
    complete_settings,
    meas_var_range,
    settings_note,
    spread_tracks,
    with_q_curve,
)
from torchsvs.fitting.tuning import FitResult, self_tune
from torchsvs.recipes import KALMAN_TWINS, LAGGED, Settings
from torchsvs.sample_accuracy import (
    accuracy_of_terms,
    anchored_fit,
    probed_terms,
    sample_blend,
    sample_terms,
)

#: Candidates of ``--estimator auto``, in the order they are tried (ties keep the first).
CANDIDATES = ("ks", "svstps", "svss", "imm")
#: The candidates are scored on the same tracks: the whole sample up to this many points, else
#: tracks spread evenly over it up to this many. The IMM's scored run costs 5-7× the KS's per
#: point (compiled: ``benchmarks/imm_track.md``; ~17× as tensor step loops, when this cap was
#: set), so its score is kept to seconds; its noises are fitted on windows of the whole sample
#: as the others' are (the search of :func:`~torchsvs.fitting.tuning.self_tune`, seconds).
#: Unfitted, the IMM smoother left ``auto`` 1.095x ``imm --fit`` on simulated hard turns
#: (recorded-tracks benchmark); skipped on samples over this size, it left ``auto`` 1.09x the
#: IMM on 10,337 rows of airliners at 5 s and 10 s scans.
IMM_POINTS = 10_000
#: Each candidate is scored by its estimated error e times 1 + CAUTION·(se/e)², se its standard
#: error. An estimate as uncertain as itself is penalised heavily (an estimator very sensitive
#: to its input has an uncertain divergence term, and one probe can flatter it: 17 ± 17 m was
#: claimed against a true 83 m). A small se barely counts: the candidates are scored on the same
#: data, so their difference is surer than either se says, and a penalty linear in se chose a
#: less noisy estimate over a lower one (svss 58.2 ± 2.9 over ks 56.6 ± 4.0 m; true 54.4, 52.4).
CAUTION = 2.0
#: A later candidate replaces the one chosen so far only where its score is lower and its
#: estimated MSE is below the incumbent's by more than this many standard errors of their
#: difference, paired chunk by chunk on the same tracks (:func:`compared`): the first
#: candidate, the Kalman smoother, keeps near-ties, which the probes' draw would otherwise
#: decide (taxiing aircraft at σ 10 m: the IMM chosen at 5.86 m against the smoother's 5.38 m).
#: With one probe, one ``q`` and the noise as read, ``auto`` came out 1.0008-1.0023x the Kalman
#: smoother on 6 of the recorded-tracks benchmark's 44 runs and 1.04x on taxiing aircraft at
#: σ 3 m (the IMM "surely" lower, -0.71 ± 0.26 m² per point; with 16 probes -0.62 ± 1.4); with
#: :func:`compared` at most 1.0008 (the smoother's own fit), mean 0.968 (was 0.967: the IMM's
#: 1.5-2.6% gains on airliners at their own report times are no longer sure).
SWITCH_ERRORS = 1.0


def surely_lower(change: float, change_se: float) -> bool:
    """Whether a challenger's estimated MSE is surely below the incumbent's: ``change`` (the
    challenger's less the incumbent's, m² per point, paired) below 0 by more than
    :data:`SWITCH_ERRORS` standard errors ``change_se``; too little data to say (NaN): not. The
    rule of ``auto`` (the Kalman smoother the first incumbent) and of :func:`checked_layer` (the
    Kalman twin the incumbent)."""
    return change + SWITCH_ERRORS * change_se < 0.0


def _error_text(change_se: float) -> str:
    """A paired difference's standard error as printed (of one chunk it is unknown)."""
    return f"{change_se:.2g}" if math.isfinite(change_se) else "? (too little data)"


def caution_score(estimate: float, standard_error: float) -> float:
    """The score ``--estimator auto`` ranks candidates by (lower is better, see CAUTION)."""
    if not estimate > 0:
        return estimate
    se = standard_error if math.isfinite(standard_error) else 0.0  # (one chunk: no se)
    return estimate * (1.0 + CAUTION * (se / estimate) ** 2)


@dataclass
class Choice:
    """What ``--estimator auto`` chose, and from what (the ``fit`` of a :class:`TrackRun`)."""

    settings: Settings  #: the winner's fitted settings
    seconds: float = 0.0
    #: one row per candidate: estimator, estimated RMSE, its standard error, fit seconds,
    #: what the fit learned (or why the candidate was skipped)
    candidates: list[dict[str, Any]] = field(default_factory=list)
    stages: list[str] = field(default_factory=list)

    @property
    def chosen(self) -> str:
        """The chosen candidate's name in the table (a blend's: both)."""
        return self.settings.name

    def table(self) -> str:
        lines = ["candidate  estimated position error (m)   fit (s)  settings"]
        for row in self.candidates:
            if row.get("skipped"):
                lines.append(f"{row['estimator']:<10} skipped: {row['skipped']}")
                continue
            mark = " <- chosen" if row["estimator"] == self.chosen else ""
            change = ""
            if "mse_change" in row:  # against the candidate chosen before it, paired
                se = _error_text(row["mse_change_se"])
                change = f"  (MSE {row['mse_change']:+.3g} ± {se} m²)"
            lines.append(
                f"{row['estimator']:<10} {row['estimated_position_rmse']:8.3g} ± "
                f"{row['standard_error']:<8.2g}            {row['seconds']:6.1f}  "
                f"{row['learned']}{change}{mark}"
            )
        return "\n".join(lines)

    def summary(self) -> str:
        blend = self.settings.blend
        chosen = self.settings.estimator
        if blend is not None:
            chosen += f" blended with {blend.estimator} (weight {self.settings.blend_weight:.2f})"
        return (
            f"auto: {chosen} chosen of {len(self.candidates)} candidates by "
            f"estimated position error ({self.seconds:.1f} s)\n" + self.table()
        )


def choose_estimator(
    settings: Settings,
    sample: RecordedTracks,
    candidates: tuple[str, ...] = CANDIDATES,
    say: Callable[[str], None] | None = None,
    check_layer: bool = True,
    own_q: bool = False,
    blend: bool = True,
    gross: tuple[int, int] | None = None,
    **fit_options: Any,
) -> Choice:
    """The candidate of the lowest truth-free error estimate on ``sample``, each tuned by SURE.

    Args:
        settings: what the user gave (``estimator`` is ignored; a given ``meas_var`` is the
            sensor's noise, else it is read off the data once for every candidate).
        sample: the tracks to fit and score on (float64).
        candidates: estimator names of :data:`~torchsvs.estimator_names.ESTIMATORS`.
        say: where to print progress.
        check_layer: an SVSF-family candidate whose boundary layer the user left open is
            what ``--estimator svss --fit`` would run: where its limit does not surely help
            against its Kalman twin, a candidate before it (:func:`checked_layer`), it is that
            twin and not scored again.
        own_q: the run gives each track its own ``q`` (the layer check compares so).
        blend: try the chosen candidate blended with the next best (:func:`blend_candidate`).
        gross: (positions set aside, positions measured) where the sample's sensor errs
            grossly (:func:`~torchsvs.fitting.outliers.has_gross_errors`): the SVSF family's
            layer is not kept (:func:`checked_layer`).
        fit_options: keyword arguments of :func:`~torchsvs.fitting.tuning.self_tune`.
    """
    say = say or (lambda _: None)
    start = time.perf_counter()
    base = complete_settings(replace(settings, estimator="ks", psi=None), sample)
    say(settings_note(base))
    noise: dict[str, Any] = {
        "meas_var": base.meas_var,
        "noise": base.noise,
        "meas_std_se": base.meas_std_se,
        "noise_spread": base.noise_spread,
    }
    points = int((~sample.z[..., 0].isnan()).sum())
    scored = sample
    if "imm" in candidates and points > IMM_POINTS:
        scored = spread_tracks(sample, IMM_POINTS)
        shown = int((~scored.z[..., 0].isnan()).sum())
        say(f"auto: candidates scored on {len(scored)} of {len(sample)} tracks ({shown} points)")
    options = dict(fit_options)
    options["known_noise"] = True  # read once above (or given): SURE in its units
    rows: list[dict[str, Any]] = []
    fits: dict[str, FitResult] = {}  # the candidates' fits, by name
    best: Settings | None = None
    best_rmse = math.inf
    for name in candidates:
        if name == "imm" and sample.z.shape[-1] not in (2, 3):
            rows.append({"estimator": name, "skipped": "turns need 2 or 3 position axes"})
            continue
        if name == "svstps" and base.velocity and "svss" in candidates:
            # The variable boundary layer's gain is the Kalman gain of its inflated prior, so
            # the SVSS's innovation gain equals it and both smoothers are the same estimator.
            rows.append({"estimator": name, "skipped": "the same estimator as svss here"})
            continue
        if name == "svstps" and not base.velocity:
            # The H⁺ mode never corrects the velocity, and the RTS pass carries its error into
            # the positions (Settings refuse svstps without velocity).
            rows.append({"estimator": name, "skipped": "diverges in the H⁺ mode"})
            continue
        tick = time.perf_counter()
        # What the user gave (q, ψ, lag) is each candidate's start; the rest is read off the data.
        open_settings = replace(settings, estimator=name, chosen_from=None, **noise)
        candidate = complete_settings(open_settings, sample)
        try:
            fit = self_tune(candidate, sample, **options)
            fit = anchored_fit(fit, candidate, sample) if own_q else fit  # (as the run runs it)
        except torch.linalg.LinAlgError as err:  # (the others still stand: one is chosen)
            if name == candidates[0]:
                raise
            say(f"auto: {name} skipped: its fit failed ({err})")
            rows.append({"estimator": name, "skipped": f"its fit failed numerically ({err})"})
            continue
        fitted = fit.settings
        twin = fits.get(KALMAN_TWINS.get(name, ""))
        check = None
        if check_layer and twin is not None and settings.psi is None and fitted.velocity:
            extra = fit.parameters - twin.parameters
            check = checked_layer(fitted, twin.settings, scored, extra, own_q, gross)
            say(check.line())
            if not check.kept:
                skipped = f"{twin.settings.estimator} here: {check.why_not()}"
                rows.append({"estimator": name, "skipped": skipped})
                continue
        fits[name] = fit
        learned = fit.stages[-1].split(": ", 1)[-1] if fit.stages else ""
        terms = sample_terms(fitted, scored)
        found = accuracy_of_terms(fitted, terms)
        seconds = time.perf_counter() - tick
        row = {
            "estimator": name,
            "estimated_position_rmse": found.estimated_rmse,
            "standard_error": found.standard_error,
            "seconds": seconds,
            "learned": learned,
        }
        say(f"auto: {name} estimated {found.estimated_rmse:.3g} m ({seconds:.1f} s)")
        score = caution_score(found.estimated_rmse, found.standard_error)
        surely = True
        if best is not None:
            extra = fit.parameters - fits[best.estimator].parameters
            against: Comparison
            if check is not None and twin is not None and best is twin.settings:
                against = check  # (the layer check compared it with the one chosen so far)
            else:
                against = compared(best, fitted, scored, extra, own_q)
            row["mse_change"], row["mse_change_se"] = -against.change, against.change_se
            surely = against.sure
        rows.append(row)
        if score < best_rmse and surely:
            best, best_rmse = fitted, score
    if best is None:
        raise ValueError(
            "tracks: no candidate of --estimator auto could be scored (too few observed "
            "positions); choose an estimator (--estimator ks)"
        )
    partner = _partner(best, rows, fits)
    if blend and partner is not None:
        tick = time.perf_counter()
        tried = blend_candidate(best, partner, scored, own_q)
        if tried is not None:
            blended, row, sure = tried
            row["seconds"] = time.perf_counter() - tick
            say(f"auto: {row['estimator']} estimated {row['estimated_position_rmse']:.3g} m")
            rows.append(row)
            if sure:
                best = blended
    chosen = replace(best, chosen_from=[r["estimator"] for r in rows if not r.get("skipped")])
    return Choice(chosen, time.perf_counter() - start, rows)


def _partner(
    best: Settings, rows: Sequence[dict[str, Any]], fits: dict[str, FitResult]
) -> Settings | None:
    """The scored candidate of the lowest score other than ``best``, with ``best``'s outlier
    screen (a blend's estimators see the same measurements), or None."""
    # (a candidate is in fits once scored: none skipped)
    others = [
        row for row in rows if row["estimator"] in fits and row["estimator"] != best.estimator
    ]
    if not others:
        return None
    row = min(
        others,
        key=lambda r: caution_score(r["estimated_position_rmse"], r["standard_error"]),
    )
    found = fits[row["estimator"]].settings
    return replace(found, outliers=best.outliers, outlier_q=best.outlier_q)


#: A blend's weight below this, or above 1 less it, is not tried: its gain is within the
#: estimate's noise, and the blend costs both estimators' runs.
LEAST_BLEND_WEIGHT = 0.05


def blend_candidate(
    chosen: Settings, partner: Settings, sample: RecordedTracks, own_q: bool = False
) -> tuple[Settings, dict[str, Any], bool] | None:
    """The blend of ``chosen`` with ``partner`` at the weight of the least estimated MSE on
    ``sample`` (:func:`~torchsvs.sample_accuracy.sample_blend`; each track with its own
    ``q`` with ``own_q``), its row of the candidates' table, and whether it is surely below
    ``chosen`` (:func:`compared`, the weight a value learned on ``sample``); None where the
    weight is within :data:`LEAST_BLEND_WEIGHT` of 0 or 1 (one of them alone)."""
    first, second = chosen, partner
    if own_q:
        first, second = with_q_curve(first, sample), with_q_curve(second, sample)
    weight, terms = sample_blend(first, second, sample)
    if not LEAST_BLEND_WEIGHT <= weight <= 1.0 - LEAST_BLEND_WEIGHT:
        return None
    blended = replace(chosen, blend=partner, blend_weight=weight)
    found = accuracy_of_terms(blended, terms)
    against = compared(chosen, blended, sample, learned=1, own_q=own_q)
    row = {
        "estimator": blended.name,
        "estimated_position_rmse": found.estimated_rmse,
        "standard_error": found.standard_error,
        "seconds": 0.0,
        "learned": f"weight {weight:.2f} on {partner.estimator}",
        "mse_change": -against.change,
        "mse_change_se": against.change_se,
    }
    return blended, row, against.sure


TWIN_NAMES = {"kf": "the Kalman filter", "ks": "the Kalman smoother"}


def kalman_twin(settings: Settings) -> Settings:
    """The settings of an SVSF-family estimator's Kalman twin (:data:`KALMAN_TWINS`): the
    same noise and ``q``, no boundary layer (a smoother's lag kept)."""
    twin = KALMAN_TWINS[settings.estimator]
    lag = settings.lag if twin in LAGGED else None
    return replace(settings, estimator=twin, psi=None, lag=lag)


#: A comparison on the tracks a fit learned from owes the fit this much estimated MSE per value
#: learned, in units of the mean measurement variance over the points: SURE is unbiased at
#: fixed settings, and its minimum over tuned ones is low by their excess optimism
#: (Tibshirani & Rosset, "Excess optimism: how biased is the apparent error of an estimator
#: tuned by SURE?", JASA 114(526), 2019), counted here as Mallows's and Akaike's 2 per
#: parameter. The layer's fit learns ψ and γ beyond its twin's ``q``; judged on the same
#: sample without this, it kept its limit on airliners at 1 s with σ 50 m at 4.4 ± 3.9 m² per
#: point "lower", truly 0.8-1.9 higher (1.002x the smoother).
OPTIMISM_PER_PARAMETER = 2.0
#: :func:`compared` takes each estimator's SURE on the sample as the mean over up to this many
#: probes of its divergence (copies of the tracks side by side, :func:`~torchsvs.
#: sample_accuracy.probed_terms`), their spread counted in the error (:func:`probed_difference`),
#: as many as fit in
#: :data:`COMPARED_PROBE_POINTS` (at least 2). One probe's estimate of the difference moved with
#: the draw by ±250 m² per point on airliners at σ 250 m (-265 to +423 over eight draws; the
#: run's own, +423 ± 174, kept a limit that truly cost 40), by 0-40 at σ 10-50 m against gains
#: of 1-400; with 4 probes that file still kept its limit (+196 ± 160), with 16 not (+38 ± 140).
COMPARED_PROBES = 16
COMPARED_PROBE_POINTS = 200_000
#: :func:`compared` judges on tracks spread evenly over the sample up to this many points (a
#: paired difference's error on 50,000 points is a fraction of the gains at stake; on a million
#: rows the whole sample's probes took 4.4 GB and 4 s more).
COMPARED_POINTS = 50_000


@dataclass
class Comparison:
    """A challenger's estimated MSE on a sample against an incumbent's (:func:`compared`)."""

    #: the incumbent's estimated MSE less the challenger's, per point (m²): the least over the
    #: noise reading's range, less what the challenger's fit owes (``optimism``)
    change: float
    change_se: float  #: its standard error: the chunks' and the probes' together
    optimism: float  #: m² per point taken off for the values the challenger's fit learned more
    over_noise: bool  #: ``change`` the least over the noise reading's range

    @property
    def sure(self) -> bool:
        """The challenger surely lower (:func:`surely_lower`)."""
        return surely_lower(-self.change, self.change_se)


@dataclass
class LayerCheck(Comparison):
    """Whether the variable boundary layer's limit earned its place on the sample: surely lower
    than its Kalman twin (:func:`checked_layer`; the twin the incumbent)."""

    estimator: str  #: the SVSF-family estimator asked for
    settings: Settings  #: what the run uses: the layer's, or its Kalman twin's
    #: (positions set aside, positions measured) where the sample's sensor errs grossly: the
    #: layer not kept, nothing compared
    gross: tuple[int, int] | None = None

    @property
    def kept(self) -> bool:
        """The layer kept."""
        return self.gross is None and self.sure

    def why_not(self) -> str:
        """Why the layer was not kept, as the candidates' table says it."""
        if self.gross is not None:
            outliers, measured = self.gross
            return (
                f"the sensor errs grossly ({outliers} of the settings' sample's {measured} "
                "positions set aside as outliers): its boundary layer's limit is not kept"
            )
        return (
            f"its boundary layer's limit does not surely help (MSE {self.change:+.3g} ± "
            f"{_error_text(self.change_se)} m² per point)"
        )

    def line(self) -> str:
        """What the run says of the check."""
        estimator, twin = self.estimator, KALMAN_TWINS[self.estimator]
        if self.gross is not None:
            return (
                f"{estimator}: {self.why_not()}: the limit takes an innovation beyond it for a "
                "maneuver and follows it, and where the sensor errs grossly its large innovations "
                f"are more likely its errors; running without a limit, as {TWIN_NAMES[twin]} "
                "(--psi keeps a limit)"
            )
        without = f"without it ({TWIN_NAMES[twin]}, {twin}) the estimated MSE is"
        se = _error_text(self.change_se)
        how = ["SURE, paired"]
        if self.over_noise:
            how.append("the least over the noise reading's uncertainty")
        if self.optimism > 0:
            how.append(
                f"less {self.optimism:.2g} m² for the values the fit learned on these tracks"
            )
        how_text = "; ".join(how)
        if self.kept:
            return (
                f"{estimator}: the boundary layer's limit kept: {without} "
                f"{self.change:.3g} ± {se} m² per point higher, surely ({how_text})"
            )
        return (
            f"{estimator}: the boundary layer's limit does not surely help on these tracks: "
            f"{without} {self.change:+.3g} ± {se} m² per point against it ({how_text}); "
            f"running without a limit, as {TWIN_NAMES[twin]} (--psi keeps a limit)"
        )


def checked_layer(
    settings: Settings,
    twin_settings: Settings,
    sample: RecordedTracks,
    learned: int = 0,
    own_q: bool = False,
    gross: tuple[int, int] | None = None,
) -> LayerCheck:
    """The settings of an SVSF-family estimator in the variable boundary layer's mode where its
    estimated MSE on ``sample`` is below its Kalman twin's (``twin_settings``, the layer without
    a limit: :data:`KALMAN_TWINS`) by more than :data:`SWITCH_ERRORS` standard errors of their
    paired difference, else the twin's (the rule ``auto`` keeps its incumbent by, here with the
    twin as the incumbent: the simpler model, which the layer without a limit is). The limit
    acts only on innovations the model does not explain; where the tracks have none it helps
    with, it only inflates the covariance at noise (simulated hard turns at σ 50 m: the SVSS
    1.02x the Kalman smoother). Too little data to say (NaN): the twin. ``chosen_from`` of the
    returned twin's settings names both.

    Two things the sample's SURE does not know are held against the layer:

    * where the noise was read off the data, the difference must be sure at every noise level
      within :data:`~torchsvs.fitting.defaults.GUARD_ERRORS` standard errors of the reading (the
      layer and the twin differ in how much they follow the measurements, so a noise read high
      flatters the one that follows them less; airliners at irregular times, σ 50 m read as
      56 ± 17: 628 ± 104 m² per point "lower" at the reading, -69 ± 85 at its low end, truly
      higher, 1.0008x the smoother);
    * ``learned``: how many more values the layer's fit learned on ``sample`` than its twin's
      (:attr:`~torchsvs.fitting.tuning.FitResult.parameters`), each owing
      :data:`OPTIMISM_PER_PARAMETER` mean measurement variances over the sample's points.

    The two are compared as the run runs them: each track with its own ``q`` with ``own_q``
    (the run's ``q`` left open; the file's curve read off ``sample``, :func:`~torchsvs.fitting.
    defaults.with_q_curve`, not kept in the returned settings; the layer makes up for a ``q``
    too low on some tracks, which their own ``q`` does too: airliners at σ 3 m, 1.32 ± 0.91 m²
    per point "lower" at one ``q``, -0.17 ± 0.18 at their own, truly 1.007x the smoother), the
    layer's divergence the mean of several probes (:data:`COMPARED_PROBES`).

    Where the sample's sensor errs grossly (``gross``: the positions the outlier screen set
    aside and those measured, :func:`~torchsvs.fitting.outliers.has_gross_errors`), the layer is
    not kept and nothing is compared: the limit takes an innovation beyond it for a maneuver and
    follows it, and SURE, which counts white noise around the path, scores following a sensor's
    error (a bias that comes and goes) as a gain. On the faults benchmarks (1% of positions off
    by 10σ, a 3σ bias over a fifth of each track) the kept layer was 1.004-1.03x the Kalman
    smoother on every set (stop 48: with the screen off, the SVSS was hurt more than the
    smoother by the outliers themselves too).

    Measured on the recorded-tracks benchmark (the best of the family over the Kalman smoother,
    11 sets × 4 modes, and 10 more at σ 3 and 250 m × 4): with the layer the incumbent (kept
    unless SURE found it costly) 16 of the 44 above 1, the worst 1.0066; with the twin the
    incumbent at one probe, one ``q`` and the noise as read, 3 of 44 above 1 (the worst 1.0023),
    5 of 40 (1.0073); as here, none above 1.0000 of either (means 0.9980 and 0.9981; gains kept:
    0.96 on airliners at 10 s scans with ``--fit``, 0.99 on taxiing aircraft at σ 10 m and at
    irregular times, 0.98-0.99 at σ 3 m)."""
    name = settings.estimator
    twin = replace(twin_settings, chosen_from=[name, twin_settings.estimator])
    if gross is not None:
        nothing = Comparison(change=math.nan, change_se=math.nan, optimism=0.0, over_noise=False)
        return LayerCheck(**asdict(nothing), estimator=name, settings=twin, gross=gross)
    found = compared(twin_settings, settings, sample, learned, own_q)
    return LayerCheck(**asdict(found), estimator=name, settings=settings if found.sure else twin)


def compared(
    incumbent: Settings,
    challenger: Settings,
    sample: RecordedTracks,
    learned: int = 0,
    own_q: bool = False,
) -> Comparison:
    """How surely ``challenger``'s estimated MSE on ``sample`` is below ``incumbent``'s, as
    the run would run them, with what SURE on the sample does not know held against the
    challenger (:func:`checked_layer` says why each):

    * on tracks spread over ``sample`` up to :data:`COMPARED_POINTS` points;
    * each track with its own ``q`` with ``own_q`` (the file's curve read off them);
    * both estimators' divergences the mean of up to :data:`COMPARED_PROBES` probes (as many as
      fit in :data:`COMPARED_PROBE_POINTS`, at least 2), their spread in the error
      (:func:`probed_difference`; a Kalman smoother's is exact, the same at every probe);
    * where the noise was read off the data, the least sure difference over every noise level
      within :data:`~torchsvs.fitting.defaults.GUARD_ERRORS` standard errors of the reading;
    * ``learned``: how many more values the challenger's fit learned on ``sample`` than the
      incumbent's, each owing :data:`OPTIMISM_PER_PARAMETER` mean measurement variances over
      the sample's points."""
    points = int((~sample.z[..., 0].isnan()).sum())
    if points > COMPARED_POINTS:
        sample = spread_tracks(sample, COMPARED_POINTS)
        points = int((~sample.z[..., 0].isnan()).sum())
    if own_q:
        incumbent, challenger = with_q_curve(incumbent, sample), with_q_curve(challenger, sample)
    assert challenger.meas_var is not None
    probes = min(COMPARED_PROBES, max(2, COMPARED_PROBE_POINTS // max(points, 1)))
    held, drawn = (_draws(settings, sample, probes) for settings in (incumbent, challenger))
    ends = meas_var_range(challenger, GUARD_ERRORS)
    levels = [challenger.meas_var, *(ends or ())]
    # the level the challenger is least surely lower at (an unknown error: unsure at any)
    change, change_se = min(
        (probed_difference(held, drawn, level) for level in levels),
        key=lambda d: d[0] - SWITCH_ERRORS * d[1] if math.isfinite(d[1]) else -math.inf,
    )
    mean_var = sum(challenger.meas_var) / len(challenger.meas_var)
    optimism = OPTIMISM_PER_PARAMETER * learned * mean_var / points if learned > 0 else 0.0
    return Comparison(change - optimism, change_se, optimism, ends is not None)


def _draws(settings: Settings, sample: RecordedTracks, probes: int) -> list[RiskTerms]:
    """The estimator's SURE terms on ``sample`` for each of ``probes`` probes: one run for a
    Kalman filter or smoother (its divergence exact, the same at every probe)."""
    if settings.exact_divergence:
        return [sample_terms(settings, sample)] * probes
    return probed_terms(settings, sample, probes)


def probed_difference(
    incumbent: Sequence[RiskTerms], challenger: Sequence[RiskTerms], meas_var: Sequence[float]
) -> tuple[float, float]:
    """The estimated MSE per point of ``incumbent`` less ``challenger``'s, each's divergence
    estimated with the same several probes (the same chunks; paired draw by draw): the
    difference of their means, and its standard error from the chunks (:meth:`~torchsvs.
    accuracy.RiskTerms.difference`) and from the probes' spread (the draws' differences'
    variance over their number) together. A probe's cross terms reach across chunks within a
    smoother's memory, so the chunks alone do not see them."""

    def mean(draws: Sequence[RiskTerms]) -> RiskTerms:
        return RiskTerms(
            np.mean([d.residual for d in draws], axis=0),
            np.mean([d.divergence for d in draws], axis=0),
            draws[0].count,
            draws[0].track,
        )

    change, chunks_se = mean(incumbent).difference(mean(challenger), meas_var)
    if len(challenger) < 2:
        return change, chunks_se
    each = [i.difference(c, meas_var)[0] for i, c in zip(incumbent, challenger, strict=True)]
    probes_var = float(np.var(each, ddof=1)) / len(challenger)
    return change, math.sqrt(chunks_se**2 + probes_var)

"""What a run of ``torchsvs track`` did: the estimates of a block (:class:`BlockEstimates`),
the run's totals, its truth-free error estimate and warnings (:class:`TrackRun`), and its
summary, printed and written as JSON next to the output (:func:`write_summary`)."""

from __future__ import annotations

import copy
import math
from collections import Counter
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from torchsvs.accuracy import Accuracy, RiskTerms, RiskTotals
from torchsvs.accuracy import accuracy as accuracy_of
from torchsvs.datasets import RowReport, TrackBlock, TrackSteps, estimate_table
from torchsvs.datasets.steps import as_rows
from torchsvs.estimate_warnings import below_zero_estimate, gross_errors, uncertain_estimate
from torchsvs.filters.particle import DEGENERATE_SHARE
from torchsvs.fitting.defaults import meas_var_range
from torchsvs.fitting.noise_read import noise_warnings, well_below_data
from torchsvs.recipes import Settings, short
from torchsvs.step_estimates import StepEstimates

#: Share of a particle filter's steps with a degenerate sample above which a run warns.
DEGENERATE_WARNING = 0.3
#: Per-track error estimates a run keeps beyond this many tracks: the worst this many.
TRACKS_KEPT = 10_000


@dataclass
class BlockEstimates:
    """A block's estimates at its flat steps, filled group by group: each group's arrays
    placed (:meth:`place`, on the thread that estimated it) and its counts added (:meth:`add`),
    then :meth:`finish`."""

    mean: np.ndarray  #: [S, 2m] NaN where not estimated (after :meth:`finish`)
    cov: np.ndarray | None  #: [S, 2m, 2m]
    never_observed: np.ndarray  #: [K, m] bool
    notes: Counter[str] = field(default_factory=Counter)
    groups: set[int] = field(default_factory=set)  #: positions of the groups added
    risk: list[RiskTerms] = field(default_factory=list)  #: the groups' SURE terms
    #: [K] each track's factor on the settings' ``q`` (NaN: one ``q`` for all, or not estimated)
    q_factor: np.ndarray = field(default_factory=lambda: np.zeros(0))
    #: [S] bool steps set aside as outliers (:func:`~torchsvs.estimating.screen_group`), or
    #: None where the groups are not screened
    outlier: np.ndarray | None = None
    #: [S] bool the steps placed so far (the arrays are left unwritten until placed)
    placed: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=bool))

    @classmethod
    def empty(
        cls, steps: TrackSteps, covariance: bool = False, screened: bool = False
    ) -> BlockEstimates:
        """Nothing estimated yet; ``screened``: the groups will be screened for outliers (the
        output gets its ``outlier`` column, in every block alike)."""
        S, m = steps.position.shape
        # (unwritten: each page is first written by the thread placing a group's estimates
        # there, beside the other groups, not filled with NaN first; finish fills the rest)
        return cls(
            np.empty((S, 2 * m)),
            np.empty((S, 2 * m, 2 * m)) if covariance else None,
            np.zeros((steps.num_tracks, m), dtype=bool),
            q_factor=np.full(steps.num_tracks, np.nan),
            outlier=np.zeros(S, dtype=bool) if screened else None,
            placed=np.zeros(S, dtype=bool),
        )

    def place(self, part: StepEstimates) -> None:
        """A group's estimates into the block's arrays. Groups hold apart steps, so the
        threads estimating them may place theirs at once (numpy's indexed writes release the
        GIL; rows as items, :func:`~torchsvs.datasets.steps.as_rows`: twice as fast)."""
        as_rows(self.mean)[part.steps] = as_rows(np.ascontiguousarray(part.mean, self.mean.dtype))
        if self.cov is not None and part.cov is not None:
            as_rows(self.cov)[part.steps] = as_rows(np.ascontiguousarray(part.cov, self.cov.dtype))
        if part.outliers is not None:
            assert self.outlier is not None, "BlockEstimates.empty(..., screened=True)"
            self.outlier[part.outliers] = True
        self.placed[part.steps] = True

    def add(self, part: StepEstimates, placed: bool = False) -> None:
        """Counts a group's notes, error terms and factors; places its arrays too unless
        ``placed`` already (:meth:`place`)."""
        if not placed:
            self.place(part)
        self.never_observed[part.group] = part.never_observed
        self.notes.update(part.notes)
        self.groups.add(part.position)
        if part.risk is not None:
            self.risk.append(part.risk)
        if part.q_factor is not None:
            self.q_factor[part.group] = part.q_factor

    def finish(self) -> None:
        """NaN at the steps no group placed (every step, where nothing was estimated)."""
        if self.placed.all():
            return
        missing = ~self.placed
        self.mean[missing] = np.nan
        if self.cov is not None:
            self.cov[missing] = np.nan

    def table(self, block: TrackBlock, precision: str = "float64") -> Any:
        """The block's output rows (:func:`~torchsvs.datasets.estimate_table`), NaN where no
        group placed estimates (:meth:`finish`: never what the unwritten memory held)."""
        self.finish()
        return estimate_table(
            block, self.mean, self.cov, self.never_observed, self.outlier, precision
        )


@dataclass
class TrackRun:
    """What ``torchsvs track`` did."""

    report: RowReport = field(default_factory=RowReport)
    settings: Settings | None = None
    seconds: float = 0.0
    estimate_seconds: float = 0.0
    estimate_cpu_seconds: float = 0.0  #: CPU time of this process (rank 0) while estimating
    fit: Any = None  #: the fit's summary (:class:`~torchsvs.fitting.tuning.FitResult`)
    #: seconds spent reading, reading off settings (and fitting), estimating, ..., writing
    #: (rank 0's in a multi-process run, ``torchsvs.training.predict``)
    phases: dict[str, float] = field(default_factory=dict)
    risk: RiskTotals | None = None  #: the truth-free error estimate's totals
    #: estimated position RMSE per track: id → (metres, observed points, its range's low and
    #: high ends, NaN where unknown); the worst :data:`TRACKS_KEPT` when there are more tracks
    track_errors: dict[str, tuple[float, int, float, float]] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)  #: what the user must know
    #: tracks per factor on the settings' ``q`` where each track ran with its own
    q_factors: Counter[float] = field(default_factory=Counter)
    #: the factor of the tracks in :attr:`track_errors` (id → factor)
    track_q: dict[str, float] = field(default_factory=dict)
    #: the least error of the worst :data:`TRACKS_KEPT` as last kept (:meth:`keep_worst`): a
    #: track's at or below it is not among the run's worst (None until there were more)
    error_floor: float | None = None
    #: an engine's sketch of the track ids its parts held (:class:`~torchsvs.engines.
    #: id_sketch.IdSketch`: its ``merge`` adds another's), or None
    parts_ids: Any = None

    @property
    def accuracy(self) -> Accuracy | None:
        """The truth-free error estimate of the whole run (:mod:`torchsvs.accuracy`)."""
        return self.accuracy_over()

    def accuracy_over(self, axes: Sequence[int] | None = None) -> Accuracy | None:
        """The truth-free error estimate of the whole run, over the position's ``axes`` alone
        where given (the horizontal ones of a 3-D run: :meth:`axes_parts`)."""
        if self.risk is None or self.settings is None or self.risk.points == 0:
            return None
        assert self.settings.meas_var is not None
        risk = self.risk if axes is None else self.risk.of_axes(axes)

        def pick(values: Sequence[float]) -> list[float]:
            return list(values) if axes is None else [values[j] for j in axes]

        settings, given = self.settings, pick(self.settings.meas_var)
        unlike = settings.noise_above_data or settings.noise_below_data
        if unlike is not None:  # a given noise unlike the data's: at their reading, to it
            read = pick([s * s for s in unlike])
            if settings.noise_below_data is not None and not well_below_data(settings):
                return accuracy_of(risk, given, False, (given, read))  # (at it, to theirs)
            return accuracy_of(risk, read, True, (read, given))
        ends = meas_var_range(settings)
        found = accuracy_of(
            risk,
            given,
            noise_estimated=settings.noise != "given",
            meas_var_range=None if ends is None else (pick(ends[0]), pick(ends[1])),
        )
        if settings.reading_is_motion_on(axes):
            found = replace(found, noise_unknown=True)
        return found

    def axes_parts(self) -> dict[str, Accuracy]:
        """A 3-D run's error estimate of its horizontal axes (the first two position columns)
        and of its vertical one apart: the whole is dominated by the larger, and a horizontal
        error is what a 2-D track is judged by (empty for fewer axes)."""
        if self.settings is None or self.settings.meas_var is None:
            return {}
        if len(self.settings.meas_var) != 3:
            return {}
        parts = {"horizontal": self.accuracy_over((0, 1)), "vertical": self.accuracy_over((2,))}
        return {name: found for name, found in parts.items() if found is not None}

    def merge(self, other: TrackRun) -> None:
        """Adds what another run of the same settings did (another part of one dataset: the
        engines' partitions) to this one: rows, notes, error estimate, tracks, warnings."""
        self.report.add(other.report)
        if self.risk is not None and other.risk is not None:
            self.risk.merge(other.risk)
        self.estimate_seconds += other.estimate_seconds
        self.estimate_cpu_seconds += other.estimate_cpu_seconds
        for name, seconds in other.phases.items():
            self.phases[name] = self.phases.get(name, 0.0) + seconds
        self.q_factors.update(other.q_factors)
        self.track_errors.update(other.track_errors)
        self.track_q.update(other.track_q)
        self._keep_worst()
        self.warnings.extend(w for w in other.warnings if w not in self.warnings)
        if other.parts_ids is not None:
            if self.parts_ids is None:
                self.parts_ids = copy.deepcopy(other.parts_ids)
            else:
                self.parts_ids.merge(other.parts_ids)

    def add_block(self, found: BlockEstimates, steps: TrackSteps) -> None:
        """Counts a block's estimates: its notes, tracks' q factors, error estimate's terms."""
        self.report.add(steps.report)
        self.report.notes.update(found.notes)
        self.report.notes = +self.report.notes  # counts of nothing are not notes
        own = np.isfinite(found.q_factor)
        self.q_factors.update(found.q_factor[own].tolist())
        if self.risk is not None:
            for terms in found.risk:
                self.risk.add(terms)
            self.add_track_errors(found.risk, steps.ids, found.q_factor)

    def add_track_errors(
        self, terms: Sequence[RiskTerms], ids: Sequence[str], q_factor: np.ndarray | None = None
    ) -> None:
        """Adds a block's per-track error estimates (the worst :data:`TRACKS_KEPT` kept), and
        the kept tracks' q factors (``[K]``, NaN where none)."""
        assert self.settings is not None and self.settings.meas_var is not None
        m = len(self.settings.meas_var)
        joined = RiskTerms.concat(terms, m)
        rmse, points = joined.per_track(self.settings.meas_var, len(ids))
        seen = np.flatnonzero(points > 0)  # (whole arrays to Python at once: 10⁵ tracks a block)
        if self.error_floor is not None:  # (the tracks that may be among the worst kept)
            seen = seen[rmse[seen] > self.error_floor]
        levels = meas_var_range(self.settings) or ()
        low, high = joined.per_track_ranges(self.settings.meas_var, len(ids), levels)
        names = [ids[k] for k in seen.tolist()]
        values = zip(
            rmse[seen].tolist(),
            points[seen].astype(np.int64).tolist(),
            low[seen].tolist(),
            high[seen].tolist(),
            strict=True,
        )
        self.track_errors.update(zip(names, values, strict=True))
        if q_factor is not None:
            own = np.isfinite(q_factor[seen])
            picked = [name for name, keep in zip(names, own.tolist(), strict=True) if keep]
            self.track_q.update(zip(picked, q_factor[seen][own].tolist(), strict=True))
        self._keep_worst()

    def _keep_worst(self) -> None:
        """Per-track error estimates: the worst :data:`TRACKS_KEPT` once there are twice as
        many (memory bounded whatever the run's size)."""
        if len(self.track_errors) > 2 * TRACKS_KEPT:
            self.keep_worst(TRACKS_KEPT)

    def keep_worst(self, count: int = TRACKS_KEPT) -> None:
        """Keeps the worst ``count`` per-track error estimates (the first added among equal
        ones)."""
        if len(self.track_errors) <= count:
            return
        worst = sorted(self.track_errors.items(), key=lambda kv: -kv[1][0])[:count]
        self.track_errors = dict(worst)
        self.track_q = {k: v for k, v in self.track_q.items() if k in self.track_errors}
        if count >= TRACKS_KEPT:  # (a floor for keeping the worst TRACKS_KEPT, not fewer;
            # the worst of a larger set: it never falls)
            self.error_floor = worst[-1][1][0]

    def check(self) -> None:
        """Warns where the estimate is not clearly better than the raw measurements."""
        found = self.accuracy
        if found is None or self.settings is None:
            return
        name = self.settings.name  # a blend's both: its divergence is not exact
        steps = self.report.notes.get("particle_steps", 0)
        low = self.report.notes.get("particle_steps_degenerate", 0)
        if steps and low > DEGENERATE_WARNING * steps:
            self.warnings.append(
                f"{name}: the particles degenerated (effective sample size below "
                f"{DEGENERATE_SHARE:.0%} of them) at {low / steps:.0%} of the steps; there the "
                "estimate rests on a few particles or the regularised Gaussian; try more "
                "--particles or --estimator ks"
            )
        self.warnings += noise_warnings(self.settings, found.meas_std)
        apart = self.settings.axis_q
        if apart is not None:
            self.warnings.append(
                "q: the positions' axes alone want process noises far apart ("
                + ", ".join(f"{f:.2g}" for f in apart)
                + " times the file's q, in the order of the position columns): one q serves "
                "every axis, so some are smoothed too much or too little and their covariances "
                "may be too small (3-D aircraft with a noisy altitude: the horizontal error "
                "1.4 times its own, its 95% intervals holding 75%); for the best of each, "
                "estimate them apart (one run with --pos-cols of the horizontal axes, one of "
                "the altitude)"
            )
        gross = gross_errors(self.report)
        if gross is not None:
            self.warnings.append(gross)
        broken = self.report.notes.get("tracks_not_finite", 0)
        if broken:
            self.warnings.append(
                f"{name}: the estimates of {broken} tracks came out NaN or infinite (a numerical "
                "breakdown of the estimator on them): their rows are written without estimates, "
                "and the error estimate is unknown; try --estimator ks"
            )
        if found.below_zero:
            self.warnings.append(f"{name}: {below_zero_estimate(found)}")
        if found.noise_unknown:  # (the noise warnings say why; no estimate to doubt)
            return
        uncertain = uncertain_estimate(found, exact=self.settings.exact_divergence)
        if uncertain is not None:
            self.warnings.append(f"{name}: {uncertain}")
        if not found.clearly_better:
            chosen = self.settings.chosen_from is not None and not self.settings.as_twin
            if self.settings.noise == "given" and chosen:
                per_track = self.report.measurement / max(self.report.tracks, 1)
                better = (  # (not --meas-std: the user gave it)
                    "checking the noise given: with it the tracks gain little from smoothing "
                    f"(their {per_track:.3g} positions per track on average; a track of two "
                    "passes through both)"
                )
            elif not chosen:  # (an SVSF run as its twin: the user chose the family)
                better = "--estimator auto (tries the candidates, keeps the lowest estimated error)"
                if name != "ks":
                    better += " or --estimator ks"
            else:
                better = "--meas-std with the sensor's noise, if known (the noise may be misread)"
            self.warnings.append(
                f"{name}: estimated position error {found.estimated_rmse:.3g} m (up to "
                f"{found.interval[1]:.3g} m) is not clearly below the measurements' "
                f"{found.measurement_rmse:.3g} m; try {better}"
            )

    def summary_json(self) -> dict[str, Any]:
        """The run's summary as written next to the output (``<output>.summary.json``)."""
        found = self.accuracy
        settings = asdict(self.settings) if self.settings is not None else None
        out: dict[str, Any] = {
            "estimator": None if self.settings is None else self.settings.name,
            "settings": settings,
            "rows": {"total": self.report.total, "placed": self.report.placed}
            | (
                {"outliers": self.report.notes.get("outliers", 0)}
                if self.settings is not None and self.settings.screens
                else {}
            ),
            "seconds": round(self.seconds, 3),
            "phases": {k: round(v, 3) for k, v in self.phases.items()},
            "warnings": self.warnings,
        }
        if found is not None:
            # (unknown, not 0 m, where it is surely below zero: the warning says why)
            unknown = found.below_zero
            interval = [math.nan] * 2 if unknown else list(found.interval)
            unknown |= found.noise_unknown  # (its range stands)
            error = math.nan if unknown else found.standard_error
            out.update(
                estimated_position_rmse=math.nan if unknown else found.estimated_rmse,
                estimated_position_rmse_interval=interval,
                estimated_position_rmse_standard_error=error,
                measurement_rmse=found.measurement_rmse,
                meas_std=found.meas_std,
                noise=None if self.settings is None else self.settings.noise,
                points=found.points,
                method="Stein's unbiased risk estimate (no truth), torchsvs.accuracy",
            )
        for name, part in self.axes_parts().items():
            out[f"{name}_position_rmse"] = part.part_summary()
        each = found is None or not found.noise_unknown  # (else no point estimate of any)
        out["tracks"] = {
            k: {
                "estimated_position_rmse": v[0] if each else math.nan,
                # (None: a track of one chunk of steps, nothing to spread, or a range below zero)
                "estimated_position_rmse_interval": None if math.isnan(v[2]) else [v[2], v[3]],
                "points": v[1],
            }
            | ({"q_factor": self.track_q[k]} if k in self.track_q else {})
            for k, v in sorted(self.track_errors.items(), key=lambda kv: -kv[1][0])[:TRACKS_KEPT]
        }
        listed = len(out["tracks"])  # (the worst TRACKS_KEPT: a bounded summary, said so)
        out["tracks_listed"] = f"{listed:,} of {self.report.tracks:,}, the largest error first"
        if self.q_factors:
            out["q_per_track"] = {
                "line": self.q_factor_line(),
                "tracks_per_factor": {f"{k:.6g}": v for k, v in sorted(self.q_factors.items())},
            }
        if self.fit is not None:
            out["fit"] = self.fit.summary()
            table = getattr(self.fit, "candidates", None)
            if table:
                out["candidates"] = table
        return out

    def q_factor_line(self) -> str:
        """How the tracks' own ``q`` spread around the file's."""
        factors = np.array(sorted(self.q_factors.elements()))
        window = None if self.settings is None else self.settings.q_window
        if window is not None:  # (a track's factor: the geometric mean of its steps')
            return (
                f"q per step: the factors' passes weighted by their SURE over {window} steps "
                f"around each, the tracks' "
                f"{factors.min():.3g}-{factors.max():.3g}× the file's on average (median "
                f"{float(np.median(factors)):.3g}); --no-step-q for one q per track, "
                "--shared-q for one q"
            )
        own = int((factors != 1.0).sum())
        kinds = None if self.settings is None else self.settings.q_kinds
        return (
            f"q per track: {own} of {len(factors)} tracks with their own, "
            f"{factors.min():.3g}-{factors.max():.3g}× the file's (median "
            f"{float(np.median(factors)):.3g})"
            + (f", shrunk toward their kind's ({len(kinds)} by interval, speed)" if kinds else "")
            + "; --shared-q for one q"
        )

    def summary(self) -> str:
        lines = [self.report.summary()]
        if self.settings is not None:
            lines.append("settings: " + settings_line(self.settings))
        if self.q_factors:
            lines.append(self.q_factor_line())
        found = self.accuracy
        if found is not None:
            lines.append(found.line())
            parts = self.axes_parts()
            if parts:
                lines.append(
                    "  of it: " + "; ".join(p.part_line(name) for name, p in parts.items())
                )
        lines.extend(f"warning: {w}" for w in self.warnings)
        steps = self.report.placed
        lines.append(
            f"{self.seconds:.1f} s in all, {self.estimate_seconds:.1f} s estimating "
            f"({self.estimate_cpu_seconds:.1f} s CPU; "
            f"{1e6 * self.estimate_seconds / max(steps, 1):.2f} µs per row placed)"
        )
        if self.phases:
            lines.append(self.phases_line())
        return "\n".join(lines)

    def phases_line(self) -> str:
        """The phases' seconds; with ``waiting`` (reading and writing beside the estimating,
        :func:`~torchsvs.tracking.track_file`), how long the rest waited for them."""
        phases = dict(self.phases)
        waiting = phases.pop("waiting", None)
        timed = ", ".join(f"{k} {v:.1f} s" for k, v in phases.items())
        if waiting is None:
            return f"phases: {timed}, other {self.seconds - sum(phases.values()):.1f} s"
        beside = phases.get("reading", 0.0) + phases.get("writing", 0.0)
        rest = self.seconds - (sum(phases.values()) - beside) - waiting
        return (
            f"phases: {timed} (reading and writing beside the estimating: waited for "
            f"{waiting:.1f} s), other {rest:.1f} s"
        )


def settings_line(settings: Settings) -> str:
    """The settings as the run's summary prints them: those set, a blend's second estimator by
    what it sets otherwise (the summary file has them all)."""
    fields = asdict(settings)
    blend = fields.pop("blend")
    # (q_curve: 13 numbers, q_kinds: 15 a kind; track_breaks: said where it is set)
    hidden = {"q_curve", "q_kinds"} | ({"blend_weight"} if blend is None else set())
    hidden |= set() if fields["track_breaks"] else {"track_breaks"}
    shown = {k: v for k, v in fields.items() if v is not None and k not in hidden}
    if blend is not None:
        hidden |= {"estimator", "blend", "blend_weight"}
        own = {k: v for k, v in blend.items() if v is not None and k not in hidden}
        inner = ", ".join(f"{k}={short(v)}" for k, v in own.items() if v != fields.get(k))
        shown["blend"] = f"{blend['estimator']}({inner})"
    return ", ".join(f"{k}={short(v)}" for k, v in shown.items())


def summary_path(target: str | Path) -> Path:
    """Where ``torchsvs track`` writes its JSON summary: ``out.csv`` → ``out.summary.json``."""
    return Path(target).with_suffix(".summary.json")


def write_summary(run: TrackRun, path: Path) -> None:
    """The run's summary (:meth:`TrackRun.summary_json`) as JSON."""

    path.write_text(_json_text(run.summary_json()) + "\n")


def _json_text(summary: dict[str, Any]) -> str:
    """``summary`` as JSON a key to a line, and a line to each of a dict value's entries
    (the tracks' error estimates: 20,000 of them): what ``json.dumps(indent=1)`` shows, by the
    C encoder (the indented one is Python's, 0.4 s on 20,000 tracks), one encoder for all
    (a call of ``json.dumps`` makes one: twice the time). A number that is not finite (an
    error unknown: NaN) is written ``null``: strict JSON has no NaN, and readers refuse it."""
    import json

    strict = json.JSONEncoder(default=_json_default, allow_nan=False).encode

    def dump(value: Any) -> str:
        try:
            return strict(value)
        except ValueError:  # (a NaN or an infinity inside)
            return strict(_finite(value))

    lines = []
    for key, value in summary.items():
        if isinstance(value, dict) and value:
            inner = ",\n".join(f"  {dump(k)}: {dump(v)}" for k, v in value.items())
            lines.append(f" {dump(key)}: {{\n{inner}\n }}")
        else:
            lines.append(f" {dump(key)}: {dump(value)}")
    return "{\n" + ",\n".join(lines) + "\n}"


def _finite(value: Any) -> Any:
    """``value`` with each number that is not finite (within dicts and lists too) as None."""
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_finite(v) for v in value]
    if isinstance(value, (float, np.floating)):
        return float(value) if np.isfinite(value) else None
    return value


def _json_default(value: Any) -> Any:
    if isinstance(value, (np.integer, np.floating)):
        return value.item()
    raise TypeError(f"not JSON: {type(value).__name__}")

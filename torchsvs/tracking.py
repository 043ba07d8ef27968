"""Tracking recorded files: the loop behind ``torchsvs track``.

A file is read in blocks of complete tracks (:func:`~torchsvs.datasets.track_blocks`); the
estimator is built from the settings (:mod:`torchsvs.recipes`) with what the user left open read
off the first block (:func:`torchsvs.fitting.defaults.complete_settings`), tuned on the file
itself with ``--fit`` (:func:`torchsvs.fitting.tuning.self_tune`) or chosen among several with
``auto`` (:mod:`torchsvs.fitting.selection`); each block is then estimated group by group
(:func:`torchsvs.estimating.estimate_group`) and written. Every run estimates its own error
without truth (:mod:`torchsvs.accuracy`) and warns where it is not clearly below the
measurements'.
"""

from __future__ import annotations

import time
from collections import Counter
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
import torch
from torch import nn

from torchsvs.accuracy import Accuracy, RiskTerms, RiskTotals
from torchsvs.accuracy import accuracy as accuracy_of
from torchsvs.datasets import (
    Columns,
    EstimateWriter,
    RecordedTracks,
    RowReport,
    TrackBlock,
    TrackSteps,
    estimate_table,
    track_blocks,
)
from torchsvs.datasets.paths import check_output
from torchsvs.estimating import (
    PROBE_SEED,
    GroupBatch,
    StepEstimates,
    centred,
    estimate_group,
    group_batch,
    lowered_noise,
    run_estimator,
    run_result,
    sample_accuracy,
    scaled_q,
    settings_q_factors,
)
from torchsvs.filters.particle import DEGENERATE_SHARE
from torchsvs.fitting.defaults import (
    IMM_QUIET,
    TURN_RATE_SCALE,
    complete_settings,
    imm_base_q,
    meas_var_range,
    screened,
    settings_note,
    turn_settings,
    typical_speed,
    with_q_curve,
)
from torchsvs.fitting.selection import choose_estimator
from torchsvs.fitting.tuning import self_tune
from torchsvs.recipes import (
    DEFAULT_LAG,
    ESTIMATORS,
    FILTERS,
    PSI_IN_SIGMAS,
    PSI_LIMIT_IN_SIGMAS,
    Settings,
    compute_dtype,
    make_estimator,
    make_model,
    rule_of_thumb_psi,
)

# The names of torchsvs.tracking; those of the recipes, the defaults and estimating live in
# torchsvs.recipes, torchsvs.fitting.defaults and torchsvs.estimating (kept here for users).
__all__ = [
    "DEFAULT_LAG",
    "DEGENERATE_WARNING",
    "ESTIMATORS",
    "FILTERS",
    "IMM_QUIET",
    "NOISE_SPREAD_WARNING",
    "PROBE_SEED",
    "PSI_IN_SIGMAS",
    "PSI_LIMIT_IN_SIGMAS",
    "TRACKS_KEPT",
    "TURN_RATE_SCALE",
    "BlockEstimates",
    "GroupBatch",
    "Settings",
    "StepEstimates",
    "TrackRun",
    "centred",
    "complete_settings",
    "estimate_group",
    "group_batch",
    "imm_base_q",
    "load_parameters",
    "make_estimator",
    "make_model",
    "meas_var_range",
    "prepare_estimator",
    "rule_of_thumb_psi",
    "run_estimator",
    "run_result",
    "sample_accuracy",
    "saved_settings",
    "scaled_q",
    "settings_note",
    "summary_path",
    "timed",
    "track_file",
    "settings_q_factors",
    "turn_settings",
    "typical_speed",
    "with_q_curve",
    "write_summary",
]

Item = TypeVar("Item")

#: Share of a particle filter's steps with a degenerate sample above which a run warns.
DEGENERATE_WARNING = 0.3
#: Between-track spread of the noise read off the data (relative) above which a run warns:
#: 0.27 on gliders and survey aircraft at 6-33 s reports, at most 0.12 on the benchmark's other
#: recorded kinds (``experiments/results/recorded_tracks.md``).
NOISE_SPREAD_WARNING = 0.2
#: Per-track error estimates a run keeps beyond this many tracks: the worst this many.
TRACKS_KEPT = 10_000


@dataclass
class BlockEstimates:
    """A block's estimates at its flat steps, filled group by group (:meth:`add`)."""

    mean: np.ndarray  #: [S, 2m] NaN until estimated
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

    @classmethod
    def empty(
        cls, steps: TrackSteps, covariance: bool = False, screened: bool = False
    ) -> BlockEstimates:
        """Nothing estimated yet; ``screened``: the groups will be screened for outliers (the
        output gets its ``outlier`` column, in every block alike)."""
        S, m = steps.position.shape
        return cls(
            np.full((S, 2 * m), np.nan),
            np.full((S, 2 * m, 2 * m), np.nan) if covariance else None,
            np.zeros((steps.num_tracks, m), dtype=bool),
            q_factor=np.full(steps.num_tracks, np.nan),
            outlier=np.zeros(S, dtype=bool) if screened else None,
        )

    def add(self, part: StepEstimates) -> None:
        self.mean[part.steps] = part.mean
        if self.cov is not None and part.cov is not None:
            self.cov[part.steps] = part.cov
        self.never_observed[part.group] = part.never_observed
        self.notes.update(part.notes)
        self.groups.add(part.position)
        if part.risk is not None:
            self.risk.append(part.risk)
        if part.q_factor is not None:
            self.q_factor[part.group] = part.q_factor
        if part.outliers is not None:
            assert self.outlier is not None, "BlockEstimates.empty(..., screened=True)"
            self.outlier[part.outliers] = True

    def table(self, block: TrackBlock) -> Any:
        """The block's output rows (:func:`~torchsvs.datasets.estimate_table`)."""
        return estimate_table(block, self.mean, self.cov, self.never_observed, self.outlier)


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
    #: estimated position RMSE per track: id → (metres, observed points); the worst
    #: :data:`TRACKS_KEPT` when there are more tracks
    track_errors: dict[str, tuple[float, int]] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)  #: what the user must know
    #: tracks per factor on the settings' ``q`` where each track ran with its own
    q_factors: Counter[float] = field(default_factory=Counter)
    #: the factor of the tracks in :attr:`track_errors` (id → factor)
    track_q: dict[str, float] = field(default_factory=dict)

    @property
    def accuracy(self) -> Accuracy | None:
        """The truth-free error estimate of the whole run (:mod:`torchsvs.accuracy`)."""
        if self.risk is None or self.settings is None or self.risk.points == 0:
            return None
        assert self.settings.meas_var is not None
        return accuracy_of(
            self.risk,
            self.settings.meas_var,
            noise_estimated=self.settings.noise != "given",
            meas_var_range=meas_var_range(self.settings),
        )

    def add_block(self, found: BlockEstimates, steps: TrackSteps) -> None:
        """Counts a block's estimates: its notes, tracks' q factors, error estimate's terms."""
        self.report.add(steps.report)
        self.report.notes.update(found.notes)
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
        rmse, points = RiskTerms.concat(terms, m).per_track(self.settings.meas_var, len(ids))
        for k in np.flatnonzero(points > 0):
            self.track_errors[ids[int(k)]] = (float(rmse[k]), int(points[k]))
            if q_factor is not None and np.isfinite(q_factor[k]):
                self.track_q[ids[int(k)]] = float(q_factor[k])
        if len(self.track_errors) > 2 * TRACKS_KEPT:
            worst = sorted(self.track_errors.items(), key=lambda kv: -kv[1][0])[:TRACKS_KEPT]
            self.track_errors = dict(worst)
            self.track_q = {k: v for k, v in self.track_q.items() if k in self.track_errors}

    def check(self) -> None:
        """Warns where the estimate is not clearly better than the raw measurements."""
        found = self.accuracy
        if found is None or self.settings is None:
            return
        name = self.settings.estimator
        steps = self.report.notes.get("particle_steps", 0)
        low = self.report.notes.get("particle_steps_degenerate", 0)
        if steps and low > DEGENERATE_WARNING * steps:
            self.warnings.append(
                f"{name}: the particles degenerated (effective sample size below "
                f"{DEGENERATE_SHARE:.0%} of them) at {low / steps:.0%} of the steps; there the "
                "estimate rests on a few particles or the regularised Gaussian; try more "
                "--particles or --estimator ks"
            )
        spread = self.settings.noise_spread
        if self.settings.noise == "data" and spread is not None and spread > NOISE_SPREAD_WARNING:
            self.warnings.append(
                f"measurement noise: read off each track alone it differs between tracks by "
                f"about {spread:.0%}, more than their own uncertainty: one noise level does not "
                "fit every track (different sensors, or motion the model does not follow at "
                "these report times), and the error estimate rests on it; give --meas-std with "
                "the sensor's noise if known"
            )
        lowered = self.settings.noise_lowered_from
        if lowered is not None:
            self.warnings.append(
                f"measurement noise: read off the data as {_short(lowered)} m, at which the "
                f"Kalman smoother was not clearly below the measurements over that reading's "
                f"uncertainty; ran at its low end, {_short(found.meas_std)} m (a noise read too "
                "high smooths away motion the model does not follow); give --meas-std with the "
                "sensor's noise if known"
            )
        if not found.clearly_better:
            if self.settings.chosen_from is None:
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
            "estimator": None if self.settings is None else self.settings.estimator,
            "settings": settings,
            "rows": {"total": self.report.total, "placed": self.report.placed}
            | (
                {"outliers": self.report.notes.get("outliers", 0)}
                if self.settings is not None and self.settings.screens
                else {}
            ),
            "seconds": round(self.seconds, 3),
            "warnings": self.warnings,
        }
        if found is not None:
            out.update(
                estimated_position_rmse=found.estimated_rmse,
                estimated_position_rmse_interval=list(found.interval),
                estimated_position_rmse_standard_error=found.standard_error,
                measurement_rmse=found.measurement_rmse,
                meas_std=found.meas_std,
                noise=None if self.settings is None else self.settings.noise,
                points=found.points,
                method="Stein's unbiased risk estimate (no truth), torchsvs.accuracy",
            )
        out["tracks"] = {
            k: {"estimated_position_rmse": v[0], "points": v[1]}
            | ({"q_factor": self.track_q[k]} if k in self.track_q else {})
            for k, v in sorted(self.track_errors.items(), key=lambda kv: -kv[1][0])
        }
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
        own = int((factors != 1.0).sum())
        return (
            f"q per track: {own} of {len(factors)} tracks with their own, "
            f"{factors.min():.3g}-{factors.max():.3g}× the file's (median "
            f"{float(np.median(factors)):.3g}); --shared-q for one q"
        )

    def summary(self) -> str:
        lines = [self.report.summary()]
        if self.settings is not None:
            shown = {k: v for k, v in asdict(self.settings).items() if v is not None}
            shown.pop("q_curve", None)  # thirteen numbers: the summary file has them
            lines.append("settings: " + ", ".join(f"{k}={_short(v)}" for k, v in shown.items()))
        if self.q_factors:
            lines.append(self.q_factor_line())
        found = self.accuracy
        if found is not None:
            lines.append(found.line())
        lines.extend(f"warning: {w}" for w in self.warnings)
        steps = self.report.placed
        lines.append(
            f"{self.seconds:.1f} s in all, {self.estimate_seconds:.1f} s estimating "
            f"({self.estimate_cpu_seconds:.1f} s CPU; "
            f"{1e6 * self.estimate_seconds / max(steps, 1):.2f} µs per row placed)"
        )
        if self.phases:
            rest = self.seconds - sum(self.phases.values())
            timed = ", ".join(f"{k} {v:.1f} s" for k, v in self.phases.items())
            lines.append(f"phases: {timed}, other {rest:.1f} s")
        return "\n".join(lines)


def _short(value: Any) -> str:
    if isinstance(value, float):
        return f"{value:.4g}"
    if isinstance(value, list):
        return "[" + ", ".join(_short(v) for v in value) + "]"
    return str(value)


def track_file(
    source: str | Path,
    target: str | Path,
    settings: Settings,
    *,
    columns: Columns | None = None,
    fit: bool = False,
    fit_options: dict[str, Any] | None = None,
    checkpoint: str | Path | None = None,
    save: str | Path | None = None,
    covariance: bool = False,
    whole: bool | None = None,
    block_rows: int = 1 << 18,
    max_cells: int = 1 << 19,
    dtype: torch.dtype = torch.float32,
    progress: bool = True,
    log: Callable[[str], None] | None = None,
    accuracy: bool = True,
    summary: bool = True,
) -> TrackRun:
    """Estimates every track of a file and writes one output row per input row.

    The file is read in blocks of complete tracks (``whole=None``: the whole file at once when
    it is under 256 MB, else streamed; streaming needs each track's rows contiguous). Settings
    the user left open are read off the first block
    (:func:`~torchsvs.fitting.defaults.complete_settings`); with ``fit`` the estimator is tuned
    on the first block's tracks (up to ``fit_options["tracks"]``) without truth before anything
    is written. Each block is estimated in groups of tracks of similar
    length of at most ``max_cells`` padded steps, so memory stays bounded.

    Args:
        source, target: input and output files (``.csv`` or ``.parquet`` each).
        settings: the estimator and whatever of its settings are known.
        columns: the input's column names.
        fit: tune the estimator on the data first (:func:`~torchsvs.fitting.tuning.self_tune`).
        fit_options: keyword arguments of the fit.
        checkpoint: load the estimator's parameters from this file (``--save`` output or a
            Lightning checkpoint of :class:`~torchsvs.training.EstimatorModule`).
        save: save the settings and the (fitted) parameters here.
        covariance: also write the covariance of every estimate.
        whole: read the whole file at once (True), stream it (False) or decide by size (None).
        block_rows: rows per block when streaming.
        max_cells: padded steps per estimator call.
        dtype: of the computation (positions are centred per track, so float32 keeps its
            resolution on large coordinates).
        progress: show a progress bar (tqdm, on stderr).
        log: where to print what was read off the data (default: nowhere).
        accuracy: estimate the position error without truth (:mod:`torchsvs.accuracy`: one
            more estimator pass on probed measurements) and warn where it is not clearly
            below the measurements'.
        summary: write the run's summary as JSON next to the output (:func:`summary_path`).
    """
    from tqdm.auto import tqdm

    start = time.perf_counter()
    say = log or (lambda _: None)
    check_output(target, "target", inputs=(source,), force=True)  # never over the input
    if whole is None:
        whole = Path(source).stat().st_size < 256 << 20
    run = TrackRun()
    run.phases = dict.fromkeys(("reading", "settings", "estimating", "writing"), 0.0)
    estimator: nn.Module | None = None
    bar: Any = None
    with EstimateWriter(target) as writer:
        blocks = track_blocks(source, columns, block_rows=block_rows, whole=whole)
        for block in timed(blocks, run.phases, "reading"):
            steps = block.steps
            if estimator is None:
                tick = time.perf_counter()
                estimator, settings, run.fit = prepare_estimator(
                    steps, settings, fit, fit_options, checkpoint, save, say
                )
                run.phases["settings"] += time.perf_counter() - tick
                dtype = compute_dtype(settings.estimator, dtype)
                estimator = estimator.to(dtype)
                run.settings = settings
                assert settings.meas_var is not None
                run.risk = RiskTotals(len(settings.meas_var)) if accuracy else None
                # disable=None: no bar where stderr is not a terminal (it would stay in a log)
                bar = tqdm(
                    desc="tracks", unit=" tracks", disable=None if progress else True, leave=False
                )
            assert run.settings is not None and run.settings.meas_var is not None
            meas_std = torch.tensor(run.settings.meas_var, dtype=dtype).sqrt()
            found = BlockEstimates.empty(steps, covariance, run.settings.screens)
            tick, cpu = time.perf_counter(), time.process_time()
            for position, group in enumerate(steps.batches(max_cells)):
                batch = group_batch(steps, group, position, dtype)
                found.add(
                    estimate_group(estimator, batch, meas_std, covariance, accuracy, run.settings)
                )
                bar.update(len(group))
            run.estimate_seconds += time.perf_counter() - tick
            run.estimate_cpu_seconds += time.process_time() - cpu
            run.add_block(found, steps)
            tick = time.perf_counter()
            writer.write(found.table(block))
            run.phases["writing"] += time.perf_counter() - tick
    run.phases["estimating"] = run.estimate_seconds
    if bar is not None:
        bar.close()
    run.report.notes = +run.report.notes
    run.check()
    run.seconds = time.perf_counter() - start
    if summary:
        write_summary(run, summary_path(target))
    return run


def summary_path(target: str | Path) -> Path:
    """Where ``torchsvs track`` writes its JSON summary: ``out.csv`` → ``out.summary.json``."""
    return Path(target).with_suffix(".summary.json")


def write_summary(run: TrackRun, path: Path) -> None:
    """The run's summary (:meth:`TrackRun.summary_json`) as JSON."""
    import json

    path.write_text(json.dumps(run.summary_json(), indent=1, default=_json_default) + "\n")


def _json_default(value: Any) -> Any:
    if isinstance(value, (np.integer, np.floating)):
        return value.item()
    raise TypeError(f"not JSON: {type(value).__name__}")


def timed(items: Iterable[Item], phases: dict[str, float], name: str) -> Iterator[Item]:
    """The items of ``items``, adding the seconds spent producing each to ``phases[name]``."""
    source = iter(items)
    while True:
        tick = time.perf_counter()
        item = next(source, None)
        phases[name] = phases.get(name, 0.0) + time.perf_counter() - tick
        if item is None:
            return
        yield item


def _sample_tracks(steps: Any, fit_options: dict[str, Any] | None) -> np.ndarray:
    """The tracks the settings are read off (and a fit runs on): up to ``tracks`` of the first
    block, spread evenly over it."""
    limit = int((fit_options or {}).get("tracks", 2000))
    count = steps.num_tracks
    if count <= limit:
        return np.arange(count)
    return np.unique(np.linspace(0, count - 1, limit).round().astype(np.int64))


def prepare_estimator(
    steps: TrackSteps,
    settings: Settings,
    fit: bool = False,
    fit_options: dict[str, Any] | None = None,
    checkpoint: str | Path | None = None,
    save: str | Path | None = None,
    say: Callable[[str], None] | None = None,
) -> tuple[nn.Module, Settings, Any]:
    """The estimator of ``torchsvs track`` for a block's tracks: the settings left open read
    off them (:func:`~torchsvs.fitting.defaults.complete_settings`, on up to
    ``fit_options["tracks"]`` tracks spread over the block, their isolated outliers set aside
    first: :func:`~torchsvs.fitting.defaults.screened`), then fitted, loaded from
    ``checkpoint``, saved to ``save``, as asked. Where the noise was read off the data and the
    Kalman smoother on the sample is not clearly below the measurements, all of it is done
    again at the low end of that reading (:func:`~torchsvs.estimating.lowered_noise`).

    Returns:
        The estimator (float64), the settings it was built from, and the fit's summary (or
        ``None``).
    """
    given = settings
    say = say or (lambda _: None)
    sample = steps.pad(_sample_tracks(steps, fit_options), torch.float64)
    open_q = settings.q is None
    options = dict(fit_options or {})
    options.pop("tracks", None)
    settings, clean, summary = _settled(settings, sample, fit, options, say)
    low = lowered_noise(settings, clean) if checkpoint is None else None
    if low is not None:
        assert settings.meas_var is not None
        read = [v**0.5 for v in settings.meas_var]
        say(
            f"noise: at {_short(read)} m (read off the data) the Kalman smoother's error is not "
            f"clearly below the measurements'; running at the low end of that reading, "
            f"{_short([v**0.5 for v in low])} m"
        )
        lowered = replace(
            given,
            meas_var=low,
            noise="data",
            meas_std_se=settings.meas_std_se,
            noise_spread=settings.noise_spread,
            noise_lowered_from=read,
        )
        settings, clean, summary = _settled(lowered, sample, fit, options, say)
    if open_q and checkpoint is None:
        settings = with_q_curve(settings, clean)
    estimator = make_estimator(settings, make_model(settings))
    if checkpoint is not None:
        load_parameters(estimator, checkpoint)
    if save is not None:
        torch.save({"settings": asdict(settings), "state_dict": estimator.state_dict()}, save)
    return estimator, settings, summary


def _settled(
    settings: Settings,
    sample: RecordedTracks,
    fit: bool,
    options: dict[str, Any],
    say: Callable[[str], None],
) -> tuple[Settings, RecordedTracks, Any]:
    """The settings left open read off ``sample`` without its isolated outliers, then fitted
    or chosen (``--estimator auto``); the screened sample, and the fit's summary."""
    settings, sample, _ = screened(settings, sample)
    if settings.estimator != "auto":
        settings = complete_settings(settings, sample)
        say(settings_note(settings))
    summary: Any = None
    if settings.estimator == "auto":
        auto_options = dict(options)
        auto_options.pop("known_noise", None)
        summary = choose_estimator(settings, sample, say=say, **auto_options)
        settings = summary.settings
        say(summary.summary())
    elif fit:
        summary = self_tune(settings, sample, **options)
        settings = summary.settings
        say(summary.summary())
    return settings, sample, summary


def load_parameters(estimator: nn.Module, path: str | Path) -> None:
    """Loads an estimator's parameters from a ``--save`` file or a Lightning checkpoint of
    :class:`~torchsvs.training.EstimatorModule` (keys ``estimator.*``)."""
    state = torch.load(path, map_location="cpu", weights_only=True)
    if not isinstance(state, dict) or "state_dict" not in state:
        raise ValueError(f"checkpoint: {str(path)!r} holds no state_dict")
    weights = state["state_dict"]
    prefix = "estimator."
    if any(k.startswith(prefix) for k in weights):
        weights = {k[len(prefix) :]: v for k, v in weights.items() if k.startswith(prefix)}
    try:
        estimator.load_state_dict(weights)
    except RuntimeError as err:
        raise ValueError(
            f"checkpoint: {str(path)!r} does not fit the estimator built from these settings "
            f"({type(estimator).__name__}): {err}"
        ) from err


def saved_settings(path: str | Path) -> Settings:
    """The settings stored by ``--save``."""
    state = torch.load(path, map_location="cpu", weights_only=True)
    if not isinstance(state, dict) or "settings" not in state:
        raise ValueError(f"checkpoint: {str(path)!r} holds no torchsvs settings (a --save file)")
    return Settings(**state["settings"])

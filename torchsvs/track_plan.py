"""What every part of a track dataset is estimated with, settled once (:class:`TrackPlan`).

``torchsvs track`` reads the settings a user left open off its first block of tracks (and fits
there with ``--fit``, or chooses with ``auto``); a dataset split over many processes or machines
(Spark, Dask: :mod:`torchsvs.engines`) must do that once, on a sample, and hand every part the
same result, or each part would read its own noise and ``q`` and the estimates would depend on
how the data were split. A :class:`TrackPlan` is that result: the resolved columns, the complete
settings, the estimator's parameters, the computation's dtype and the output's precision. It
pickles, so an engine broadcasts it as it is; :func:`~torchsvs.track_table.track_table` runs it
on a table of tracks.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn

from torchsvs.datasets import Columns, RecordedTracks, TrackSteps
from torchsvs.datasets.breaks import some_tracks, split_at_breaks
from torchsvs.datasets.describe import typical_interval
from torchsvs.datasets.noise_estimate import changing_tracks
from torchsvs.datasets.tables import SAMPLE_TRACKS, block_of
from torchsvs.datasets.tracks import padded_batch
from torchsvs.datasets.writing import OUTPUT_TYPES
from torchsvs.fitting.defaults import (
    Screened,
    axes_q,
    complete_settings,
    screened,
    settings_note,
    with_q_curve,
)
from torchsvs.fitting.outliers import has_gross_errors
from torchsvs.fitting.tuning import self_tune
from torchsvs.recipes import (
    KALMAN_TWINS,
    NOISE_READ,
    Settings,
    compute_dtype,
    make_estimator,
    make_model,
    short,
)
from torchsvs.sample_accuracy import (
    anchored_fit,
    checked_below,
    checked_low,
    checked_within,
    lowered_noise,
    with_track_noise,
)
from torchsvs.selection import checked_layer, choose_estimator, kalman_twin

#: ``precision`` of the estimates written: ``"auto"`` is float32 where it keeps positions to
#: :data:`POSITION_RESOLUTION` of the measurement noise (:func:`output_precision`).
PRECISIONS = ("auto", *OUTPUT_TYPES)
#: float32 is written (``precision="auto"``) where its spacing at the largest position is at
#: most this share of the smallest measurement noise standard deviation: rounding then moves a
#: position by at most half of it, far below any estimate's own error.
POSITION_RESOLUTION = 0.01
#: Positions of the parts not yet seen may be larger than the sample's: ``"auto"`` decides at
#: this many times the sample's largest (later parts are checked: :func:`precision_warning`).
MAGNITUDE_HEADROOM = 4.0
#: Metres per degree of latitude (WGS 84, mean): a float32 degree's spacing in metres.
METRES_PER_DEGREE = 111_320.0


@dataclass(eq=False)  # (identity: its parameters are tensors, whose == is elementwise)
class TrackPlan:
    """What every table of a dataset is estimated with (:func:`plan_tracks`), settled once."""

    columns: Columns  #: resolved: positions, frame and the time unit in seconds
    settings: Settings  #: complete (noise, ``q``, ...), fitted or chosen where asked
    parameters: dict[str, Tensor]  #: the estimator's state (a checkpoint's, or the settings')
    dtype: torch.dtype = torch.float32  #: of the computation
    precision: str = "float64"  #: of the estimates written, ``"float32"`` or ``"float64"``
    #: the fit's or the choice's summary (``--fit``, ``auto``), or None; not needed to estimate
    fit: Any = field(default=None, compare=False)

    def __post_init__(self) -> None:
        if self.precision not in OUTPUT_TYPES:
            raise ValueError(
                f"precision: expected one of {list(OUTPUT_TYPES)}, got {self.precision!r}"
            )
        if self.settings.meas_var is None:
            raise ValueError("settings: expected complete settings (meas_var set): plan_tracks")

    def estimator(self) -> nn.Module:
        """The estimator, built from the settings with the plan's parameters, in its dtype."""
        estimator = make_estimator(self.settings, make_model(self.settings))
        estimator.load_state_dict(self.parameters)
        return estimator.to(self.dtype)

    @property
    def meas_std(self) -> Tensor:
        """``[m]`` the measurement noise standard deviation per axis, in the plan's dtype."""
        assert self.settings.meas_var is not None
        return torch.tensor(self.settings.meas_var, dtype=self.dtype).sqrt()

    def __getstate__(self) -> dict[str, Any]:
        # The fit's summary is for the person who ran the plan, not for the parts: sent
        # to every executor it would only cost time.
        return {**self.__dict__, "fit": None}


def plan_tracks(
    data: Any,
    settings: Settings | None = None,
    *,
    columns: Columns | None = None,
    fit: bool = False,
    fit_options: dict[str, Any] | None = None,
    checkpoint: str | Path | None = None,
    save: str | Path | None = None,
    dtype: torch.dtype = torch.float32,
    precision: str = "auto",
    block_rows: int = 1 << 18,
    log: Callable[[str], None] | None = None,
) -> TrackPlan:
    """Settles what ``settings`` leave open on a sample of the data, once: the noise and ``q``
    read off it, fitted with ``fit``, chosen with ``settings.estimator == "auto"``, as
    ``torchsvs track`` does on a file's first block.

    Args:
        data: a sample of the dataset: a ``.csv``/``.parquet`` file or Parquet dataset (its
            first blocks, up to ``fit_options["tracks"]`` tracks:
            :func:`~torchsvs.datasets.tables.block_of`), a ``pandas.DataFrame`` or a
            ``pyarrow.Table`` of track rows, or a block already read (``torchsvs track``
            plans on its first blocks, joined).
        settings: the estimator and what is known of its settings (default: ``auto``).
        columns: the data's column names (default ``track_id, time, x, y[, z]``).
        fit, fit_options, checkpoint, save: as for :func:`~torchsvs.tracking.track_file`.
        dtype: of the computation (some estimators always run in float64:
            :func:`~torchsvs.recipes.compute_dtype`).
        precision: of the estimates written: ``"float32"``, ``"float64"`` or ``"auto"``
            (:func:`output_precision`).
        log: where to print what was read off the data.
    """
    if precision not in PRECISIONS:
        raise ValueError(f"precision: expected one of {list(PRECISIONS)}, got {precision!r}")
    tracks = int((fit_options or {}).get("tracks", SAMPLE_TRACKS))
    noise = None if settings is None else settings.noise_column
    if noise is not None:  # (its column read beside the positions, as --noise-col reads it)
        columns = columns or Columns()
        if noise not in columns.extra:
            columns = replace(columns, extra=(*columns.extra, noise))
    block = block_of(data, columns, block_rows, tracks)
    estimator, settings, summary = prepare_estimator(
        block.steps, settings or Settings(estimator="auto"), fit, fit_options, checkpoint, save, log
    )
    assert settings.meas_var is not None
    if precision == "auto":
        precision = output_precision(block.steps, block.columns, settings.meas_var)
    return TrackPlan(
        block.columns,
        settings,
        estimator.state_dict(),
        compute_dtype(settings, dtype),
        precision,
        summary,
    )


def output_precision(steps: TrackSteps, columns: Columns, meas_var: list[float]) -> str:
    """``"float32"`` where float32 keeps the positions of tracks like these (at
    :data:`MAGNITUDE_HEADROOM` times their largest) to :data:`POSITION_RESOLUTION` of the
    smallest measurement noise standard deviation, else ``"float64"``: metres near an origin
    (a local frame, a sensor's) are written as float32, large map coordinates (UTM
    northings) and latitude, longitude in degrees mostly as float64."""
    return "float32" if _float32_keeps(steps, columns, meas_var, MAGNITUDE_HEADROOM) else "float64"


def plan_columns(plan: TrackPlan) -> list[str]:
    """The columns a part must hold: the id, the time, the positions and any extra."""
    cols = plan.columns
    return [cols.track_id, cols.time, *(cols.position or ()), *cols.extra]


def check_columns(available: Sequence[str], plan: TrackPlan, name: str) -> None:
    """A ValueError naming the argument ``name`` where the data lack a column of the plan."""
    missing = [c for c in plan_columns(plan) if c not in available]
    if missing:
        raise ValueError(
            f"{name}: columns {missing} of the plan not in the data (its columns: "
            f"{list(available)})"
        )


def precision_warning(plan: TrackPlan, steps: TrackSteps) -> str | None:
    """Why float32 does not keep these tracks' positions as :func:`output_precision` meant
    (positions larger than the sample's), or None."""
    assert plan.settings.meas_var is not None
    if plan.precision != "float32" or _float32_keeps(
        steps, plan.columns, plan.settings.meas_var, 1.0
    ):
        return None
    return (
        "precision: positions larger than the sample the plan was made on are written as "
        f"float32, which rounds them by more than {POSITION_RESOLUTION / 2:g} of the noise; "
        "write float64 (--precision float64, or plan_tracks(..., precision='float64'))"
    )


#: Rows whose typical interval is this many times the plan's sample's (or as many times below)
#: are said to be unlike it (:func:`interval_warning`): seconds read as milliseconds are 1,000.
UNLIKE_INTERVAL = 30.0
#: ... read off a block's first this many steps.
INTERVAL_STEPS = 20_000


def interval_warning(plan: TrackPlan, steps: TrackSteps) -> str | None:
    """Why these rows' times may not be what the plan reads them as: their typical interval
    :data:`UNLIKE_INTERVAL` times the plan's sample's or more (or as far below), or None. A
    plan settles the time unit on its sample, and rows in another unit were read in the plan's
    without a word: epoch milliseconds read as seconds came out at 2.4 times the truth's error
    (a plan on seconds), 3,560 m (the other way round; an outside probe)."""
    interval, planned = typical_interval(steps, INTERVAL_STEPS), plan.settings.interval
    if (
        not (interval > 0 and planned > 0)
        or 1 / UNLIKE_INTERVAL < interval / planned < UNLIKE_INTERVAL
    ):
        return None
    return (
        f"time: these rows' typical interval is {interval:.4g} s against {planned:.4g} s in the "
        f"sample the plan was made on (its time column read at {plan.columns.seconds_per_unit:g} "
        "s per unit): if their times are in another unit, plan on them or give the unit "
        "(--time-unit, Columns(time_unit=...)); if they are of another kind of track, the "
        "settings read off the sample may not suit them"
    )


def _float32_keeps(
    steps: TrackSteps, columns: Columns, meas_var: list[float], headroom: float
) -> bool:
    position = steps.position
    if columns.geodetic:  # written as degrees (and the altitude in metres)
        assert steps.reference is not None
        finite = steps.reference[np.isfinite(steps.reference).all(axis=1)]
        largest = float(np.abs(finite).max(initial=0.0))
        spacing = float(np.spacing(np.float32(min(largest * headroom, 360.0))))
        spacings = [spacing * METRES_PER_DEGREE] * 2
        if position.shape[1] == 3:
            spacings.append(_spacing(position[:, 2], headroom))
    else:
        spacings = [_spacing(position[:, j], headroom) for j in range(position.shape[1])]
    smallest = min(float(v) ** 0.5 for v in meas_var)
    return max(spacings) <= POSITION_RESOLUTION * smallest


def _spacing(values: np.ndarray, headroom: float) -> float:
    # (the extremes without a copy of the finite values: checked on every block)
    low, high = float(values.min(initial=np.inf)), float(values.max(initial=-np.inf))
    if math.isnan(low) or math.isnan(high):  # (missing positions: the slower reductions)
        low = float(np.nanmin(values, initial=np.inf))
        high = float(np.nanmax(values, initial=-np.inf))
    if math.isfinite(low) and math.isfinite(high):
        largest = max(abs(low), abs(high))
    else:  # nothing but NaN, or an infinity among the values
        finite = values[np.isfinite(values)]
        largest = float(np.abs(finite).max(initial=0.0))
    largest *= headroom
    return float(np.spacing(np.float32(min(largest, 3e38))))


def _sample_tracks(steps: Any, fit_options: dict[str, Any] | None) -> np.ndarray:
    """The tracks the settings are read off (and a fit runs on): up to ``tracks`` of the first
    block, spread evenly over it in the order of their ids. In that order, not the file's: the
    fit's windows and probes are drawn by position in the sample, so a file's settings (and
    ``auto``'s choice) would otherwise change with the order its tracks were written in."""
    limit = int((fit_options or {}).get("tracks", SAMPLE_TRACKS))
    order = np.argsort(np.asarray(steps.ids, dtype=str), kind="stable")
    if len(order) <= limit:
        return order
    return order[np.unique(np.linspace(0, len(order) - 1, limit).round().astype(np.int64))]


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
    ``checkpoint``, saved to ``save``, as asked. Where the noise was read off the data, each
    track runs at its own reading where the tracks differ and that is clearly better
    (:func:`~torchsvs.sample_accuracy.with_track_noise`); else, where the Kalman smoother on the
    sample is not clearly below the measurements, the run takes the low end of the file's
    reading (:func:`~torchsvs.sample_accuracy.lowered_noise`); both decided on the
    screened sample before anything is fitted or chosen (once: a fit at the reading was thrown
    away, 20 s of ``rstkf --fit`` on 5,000 rows).

    Returns:
        The estimator (float64), the settings it was built from, and the fit's summary (or
        ``None``).
    """
    saved = None if checkpoint is None else checkpoint_settings(settings, checkpoint)
    settings = saved or settings
    given = settings
    say = say or (lambda _: None)
    # the sample's tracks split at their breaks (a jump read as motion raised q 10^4 times)
    picked, breaks = split_at_breaks(some_tracks(steps, _sample_tracks(steps, fit_options)))
    sample = padded_batch(picked, np.arange(picked.num_tracks), torch.float64)
    moving = changing_tracks(sample.z)
    if bool(moving.any()) and not bool(moving.all()):  # (still tracks tell no noise, no q)
        sample = sample.subset(moving.nonzero()[:, 0])
    open_q = settings.q is None
    options = dict(fit_options or {})
    options.pop("tracks", None)
    own = checkpoint is None  # (a checkpoint's settings are its own: nothing read or checked)
    screen = None
    if own:  # the noise read and the outliers set aside once, before anything is fitted
        screen = screened(settings, sample)
        read = checked_within(screen.settings, screen.tracks)
        if read is not screen.settings:  # (the file's reading kept: screened again at it)
            settings = replace(given, **{name: getattr(read, name) for name in NOISE_READ})
            screen = screened(settings, sample)
            read = screen.settings
        own_noise = with_track_noise(read, screen.tracks)
        low = None if own_noise is not None else lowered_noise(read, screen.tracks)
        if own_noise is not None:
            chosen, line = own_noise
            say(line)
            settings = replace(given, **{name: getattr(chosen, name) for name in NOISE_READ})
            screen = None  # (screened again, each track at its own noise)
        elif low is not None:
            assert read.meas_var is not None
            std = [v**0.5 for v in read.meas_var]
            why = (
                "the Kalman smoother's error is not clearly below the measurements'"
                if not read.reading_is_motion
                else "the reading is mostly motion between reports (see the warnings)"
            )
            say(
                f"noise: at {short(std)} m (read off the data) {why}; running at the low end "
                f"of that reading, {short([v**0.5 for v in low])} m"
            )
            noise = {name: getattr(read, name) for name in NOISE_READ}
            settings = replace(given, **noise | {"meas_var": low, "noise_lowered_from": std})
            screen = None  # (screened again at that noise)
    settings, clean, summary = _settled(
        settings, sample, fit, options, say, own, own and open_q, screen
    )
    if checkpoint is None:
        settings = checked_below(settings, clean)
    if open_q and checkpoint is None:
        settings = axes_q(checked_low(with_q_curve(settings, clean), clean), clean)
    if breaks and checkpoint is None:
        settings = replace(settings, track_breaks=True)
    estimator = make_estimator(settings, make_model(settings))
    if checkpoint is not None:
        load_parameters(estimator, checkpoint)
        if saved is None:  # (a Lightning checkpoint: parameters without their settings)
            settings = _loaded_noise(settings, given, estimator, checkpoint)
    if save is not None:
        torch.save({"settings": asdict(settings), "state_dict": estimator.state_dict()}, save)
    return estimator, settings, summary


def _settled(
    settings: Settings,
    sample: RecordedTracks,
    fit: bool,
    options: dict[str, Any],
    say: Callable[[str], None],
    check_layer: bool = True,
    q_curves: bool = False,
    screen: Screened | None = None,
) -> tuple[Settings, RecordedTracks, Any]:
    """The settings left open read off ``sample`` without its isolated outliers, then fitted
    or chosen (``--estimator auto``); the screened sample, and the fit's summary. With
    ``check_layer``, an SVSF-family estimator whose boundary layer the user left open keeps its
    limit only where the sample shows it surely helps (:func:`~torchsvs.selection.checked_layer`:
    else it runs as its Kalman twin, the layer without a limit), both compared with their own
    ``q`` per track where ``q_curves`` (the run's ``q`` left open: each track will run so); not
    kept where the screen finds the sensor errs grossly (:func:`~torchsvs.fitting.outliers.
    has_gross_errors`); ``screen``: :func:`~torchsvs.fitting.defaults.screened` of these
    settings and ``sample`` already."""
    settings, sample, flagged = screen if screen is not None else screened(settings, sample)
    outliers = int(flagged.sum())
    measured = outliers + int((~torch.isnan(sample.z[..., 0])).sum())
    gross = (outliers, measured) if has_gross_errors(outliers, measured) else None
    # the layer's limit read off the data too, where the user left it open
    open_layer = check_layer and settings.estimator in KALMAN_TWINS and settings.psi is None
    if settings.estimator != "auto":
        settings = complete_settings(settings, sample)
        say(settings_note(settings))
    summary: Any = None
    completed = settings
    if settings.estimator == "auto":
        auto_options = dict(options)
        auto_options.pop("known_noise", None)
        summary = choose_estimator(
            settings,
            sample,
            say=say,
            check_layer=check_layer,
            own_q=q_curves,
            gross=gross,
            **auto_options,
        )
        settings = summary.settings
        say(summary.summary())
    elif fit:
        summary = self_tune(settings, sample, **options)
        if q_curves:
            summary = anchored_fit(summary, settings, sample)
        settings = summary.settings
        say(summary.summary())
    if open_layer and settings.velocity:
        twin = kalman_twin(completed)
        learned = 0  # how many more values the layer's fit learned on the sample than the twin's
        if fit:  # the twin fitted as the layer was (a Kalman smoother's fit: a fraction of a s)
            twin_fit = self_tune(twin, sample, **options)
            twin_fit = anchored_fit(twin_fit, twin, sample) if q_curves else twin_fit
            twin, learned = twin_fit.settings, summary.parameters - twin_fit.parameters
        check = checked_layer(settings, twin, sample, learned, q_curves, gross)
        say(check.line())
        settings = check.settings
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


#: The ``torchsvs track`` option that sets each of :class:`~torchsvs.recipes.Settings`' fields
#: (the error messages name both)
OPTION_OF = {
    "meas_var": "--meas-std",
    "noise_column": "--noise-col",
    "track_q": "--shared-q",
    "step_q": "--no-step-q",
    "outliers": "--keep-outliers",
    "velocity": "--no-velocity",
}


def _named(field_name: str) -> str:
    """A settings field and its ``torchsvs track`` option (:data:`OPTION_OF`)."""
    option = OPTION_OF.get(field_name, "--" + field_name.replace("_", "-"))
    return f"{field_name} ({option})"


def checkpoint_settings(settings: Settings, checkpoint: str | Path) -> Settings | None:
    """The settings of a run from ``checkpoint``: a ``--save`` file's own, which reproduce the
    saved run (``settings`` may leave them open, ``estimator="auto"`` and the defaults, or
    repeat them; one that differs is refused, naming it: the command line dropped it without a
    word, and the API took it beside the saved parameters it contradicts); None for a Lightning
    checkpoint, which holds parameters alone (:func:`_loaded_noise`)."""
    try:
        saved = saved_settings(checkpoint)
    except ValueError:
        return None
    open_ = Settings(estimator=saved.estimator)
    for each in fields(Settings):
        mine = getattr(settings, each.name)
        if each.name == "estimator" and mine == "auto":
            continue
        if mine != getattr(open_, each.name) and mine != getattr(saved, each.name):
            raise ValueError(
                f"settings: {_named(each.name)} = {mine!r} given, and the checkpoint "
                f"{str(checkpoint)!r} holds its own ({getattr(saved, each.name)!r}), with "
                "which its parameters were saved; leave it out to run as saved, or leave the "
                "checkpoint out"
            )
    return saved


def _loaded_noise(
    settings: Settings, given: Settings, estimator: nn.Module, checkpoint: str | Path
) -> Settings:
    """The settings with the measurement noise (and ``q``, of a model of one) that
    ``estimator``'s parameters, loaded from ``checkpoint``, hold: the error estimate and what
    the run prints are at those, not at a reading they replaced. A value ``given`` that the
    parameters contradict is refused, naming it."""
    models: list[Any] = [
        m for m in estimator.modules() if hasattr(m, "meas_cov") and hasattr(m, "q")
    ]
    if not models:
        return settings
    loaded: dict[str, Any] = {
        "meas_var": [float(v) for v in models[0].meas_cov().detach().diagonal()]
    }
    if len(models) == 1:
        loaded["q"] = float(models[0].q().detach())
    for name, value in loaded.items():
        mine = getattr(given, name)
        if mine is not None and not np.allclose(mine, value, rtol=1e-6):
            raise ValueError(
                f"settings: {_named(name)} = {mine!r} given, and the checkpoint "
                f"{str(checkpoint)!r} holds "
                f"{short(value) if isinstance(value, list) else f'{value:.6g}'}; leave it out "
                "to run at the checkpoint's, or leave the checkpoint out"
            )
    return replace(settings, **loaded, noise="given", meas_std_se=None, noise_spread=None)


def saved_settings(path: str | Path) -> Settings:
    """The settings stored by ``--save``."""
    state = torch.load(path, map_location="cpu", weights_only=True)
    if not isinstance(state, dict) or "settings" not in state:
        raise ValueError(f"checkpoint: {str(path)!r} holds no torchsvs settings (a --save file)")
    return Settings(**state["settings"])

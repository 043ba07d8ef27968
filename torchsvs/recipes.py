"""Recipes: what an estimator of ``torchsvs track`` is built from, by name.

:data:`~torchsvs.estimator_names.ESTIMATORS` names them; :class:`Settings` holds what one is
built from (noise levels, ``q``, the SVSF family's boundary layer, the IMM's mode noises, ...);
:func:`make_model` and :func:`make_estimator` build it. Filling open settings from the data is
:mod:`torchsvs.fitting.defaults`' work, running the estimator over a file
:mod:`torchsvs.estimating`'s and :mod:`torchsvs.tracking`'s.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any

import torch
from torch import nn

from torchsvs.estimator import Estimator
from torchsvs.estimator_names import ESTIMATORS
from torchsvs.filters import (
    SPVSF,
    SVSF,
    ExtendedKalmanFilter,
    KalmanFilter,
    ParticleFilter,
    RobustStudentTKalmanFilter,
    UnscentedKalmanFilter,
    VariableBoundarySVSF,
)
from torchsvs.filters.turn_imm import TurnIMM
from torchsvs.models import ConstantVelocity
from torchsvs.smoothers import SVSS, RTSSmoother, TurnIMMSmoother

#: Lag of each smoother when none is given (``None``: fixed interval). The IMM's is Kim's
#: fixed-lag smoother at 5 steps: on the recorded-tracks benchmark (``experiments.
#: recorded_tracks``, σ 10-50) lag 5 took the IMM filter's 0.58-0.86x the raw measurements to
#: 0.31-0.57x; lag 2 was 1-25% behind it, lag 20 up to 70% (a CV mode of small ``q`` carries
#: a maneuver's error rigidly back over a long window: :class:`~torchsvs.IMMSmoother`).
#: The SVSF family's smoothers over the variable boundary layer smooth the fixed interval, as the
#: Kalman smoother does (inside the layer they are the Kalman smoother); at lag 5 they were
#: 1.02-1.32x the Kalman smoother on the benchmark's sets at the same limit.
DEFAULT_LAG: dict[str, int | None] = {"ks": None, "svss": None, "svstps": None, "imm": 5}
#: Estimators whose own ``q`` per track (:func:`~torchsvs.estimating.settings_q_factors`) may
#: only rise above the file's: the factors are chosen on the Kalman filter's SURE, and a
#: Student-t filter with less ``q`` takes the turns it no longer expects for outliers and loses
#: the track (1.25x raw on 10 s scans at a third of the file's q, ``--fit`` with faults).
UPWARD_Q_ONLY = frozenset({"rstkf"})
#: The estimators a lag applies to (``imm``: Kim's fixed-lag smoother, lag 0 its filter;
#: ``auto``: to its candidates).
LAGGED = ("ks", "svss", "svstps", "imm", "auto")
#: The smoothers' default lag in the ``H⁺`` mode (``--no-velocity``): that mode corrects
#: positions only, so the velocity keeps the two-point prior's error (σ√2/Δt) for the whole
#: track, and a backward pass longer than one step carries it into the positions. Measured on
#: recorded airliners (own report times, σ 50, ``experiments.recorded_tracks``): the SVSS at lag 1
#: 0.84× the raw measurements, at lag 2 6.5×, at lag 5 26.5×.
HPLUS_LAG = 1
#: Boundary layer of the rule of thumb in the ``H⁺`` mode (``--no-velocity``), in standard
#: deviations of each step's own measurement noise (Chen et al. 2020: 4-5).
PSI_IN_SIGMAS = 5.0
#: The variable boundary layer's limit of the rule of thumb, in standard deviations of each
#: step's own innovation (:class:`~torchsvs.filters.VariableBoundarySVSF`). Chosen on simulated
#: ships, airliners, drones, irregular times and hard turns and on recorded flights: at 2 the
#: filter stays below the raw measurements also where ``q`` suits a smoother and is too small
#: for a filter in turns (10 s airliner scans); wider limits (3-4) bring the smoothers 2-10%
#: closer to the Kalman smoother on simulated tracks and lift the filter to the raw error there.
PSI_LIMIT_IN_SIGMAS = 2.0
#: The same limit for the smoothers over the layer (``svss``, ``svstps``): a smoother reads each
#: step with the steps after it, so it inflates only at an innovation the Kalman smoother would
#: not explain. Measured on the recorded-tracks benchmark's eleven sets (noise read off the
#: data, fixed interval), against the Kalman smoother: at 2 1.00-1.26x (scan1 σ50 1.22, taxi
#: σ50 1.23, turning 1.26), at 3 0.98-1.11x, at 4 0.988-1.020x (turning σ50 the 1.020).
PSI_SMOOTHER_LIMIT_IN_SIGMAS = 4.0
#: Estimators ``torchsvs track`` runs in float64 whatever its ``dtype``: the IMM's cost is its
#: step loop, not its arithmetic, and float32 left a rarely used mode's nearly singular
#: covariance indefinite (an eigenvalue -6.8 of 1.2e4, recorded airliners at 1 s, σ 10), which
#: its smoother's backward pass cannot factor.
FLOAT64 = frozenset({"imm"})


def compute_dtype(settings: Settings, dtype: torch.dtype) -> torch.dtype:
    """The dtype ``torchsvs track`` runs the estimator of ``settings`` (and of its blend) in
    when ``dtype`` is asked for (:data:`FLOAT64`)."""
    names = {settings.estimator} | ({settings.blend.estimator} if settings.blend else set())
    return torch.float64 if names & FLOAT64 else dtype


#: Estimators whose output is a filter's (each step from the past alone): their q is the
#: Kalman filter's, the others' the Kalman smoother's
#: (:func:`~torchsvs.fitting.defaults._sure_q`).
FILTERS = ("kf", "ekf", "ukf", "rstkf", "pf", "spvsf", "svsf")
#: The linear Kalman filter and smoother: their error estimate's divergence is exact.
KALMAN = ("kf", "ks")
#: The SVSF family's Kalman twins: with no limit on its variable boundary layer an SVSF is the
#: Kalman filter and an SVSS (or SVSTPS) the Kalman smoother
#: (:class:`~torchsvs.filters.VariableBoundarySVSF`; ``tests/test_svsf_defaults.py``).
KALMAN_TWINS = {"svsf": "kf", "svss": "ks", "svstps": "ks"}


@dataclass
class Settings:
    """What an estimator of :data:`ESTIMATORS` is built from (per-axis lists for an ``m``-axis
    file; the SVSF's ``psi`` has one width per corrector component, in state order)."""

    estimator: str = "ks"
    meas_var: list[float] | None = None  #: measurement noise variance per axis
    q: float | None = None  #: process noise spectral density of the CV model
    #: SVSF family's boundary layer, one value per axis (or one for all): the variable
    #: boundary layer's limit in innovation standard deviations; with ``velocity=False`` (the
    #: H⁺ mode) the width in measurement noise standard deviations. None:
    #: :func:`rule_of_thumb_psi`
    psi: list[float] | None = None
    gamma: float = 0.1  #: SVSF memory
    lag: int | None = None  #: smoother lag; None: :data:`DEFAULT_LAG`
    velocity: bool = True  #: SVSF corrects velocity (finite differences); False: the H⁺ mode
    particles: int = 350  #: particles of the PF and SPVSF
    interval: float = 1.0  #: typical sampling interval of the data (s), for the rule of thumb
    #: IMM: the CT mode's white acceleration variance per horizontal axis (m²/s⁴)
    turn_q: float | None = None
    turn_rate_q: float | None = None  #: IMM: the CT mode's turn-rate noise (rad²/s⁴)
    turn_rate_std: float | None = None  #: IMM: prior standard deviation of the turn rate (rad/s)
    switch_prob: float = 0.05  #: IMM: probability of a mode switch per step
    #: where ``meas_var`` came from: "given", "data" (read off the tracks) or "fit" (learned by
    #: likelihood); None until :func:`~torchsvs.fitting.defaults.complete_settings`
    noise: str | None = None
    #: standard error of the noise standard deviation per axis, where it was read off the data
    meas_std_se: list[float] | None = None
    #: where the noise was read off the data: how much the reading differs between tracks
    #: beyond their own uncertainty (a relative spread, :func:`~torchsvs.datasets.noise_spread`;
    #: also in ``meas_std_se``)
    noise_spread: float | None = None
    #: Where the noise read off pieces of the tracks changes within them (:func:`~torchsvs.
    #: fitting.noise_read.with_noise_read`): ``[τ, σ_low, σ_high, σ_core, σ_mean]``, the
    #: spread of ``log σ`` between a track's pieces, the quietest and noisiest tenth of the
    #: pieces' ``σ``, the reading's core and the pieces' mean: ``meas_var`` is the mean's, or
    #: the core's where the Kalman smoother does not do better at the mean
    #: (:func:`~torchsvs.sample_accuracy.checked_within`)
    noise_within: list[float] | None = None
    #: where the noise read off the data is contradicted by the covariance of the positions'
    #: second differences two reports apart (:func:`~torchsvs.datasets.noise_lags.
    #: motion_checked`): per axis that covariance over what noise at the reading makes (1 for
    #: noise), NaN on axes it does not contradict; ``meas_std_se`` takes in the difference: the
    #: reading is motion between reports
    noise_lag: list[float] | None = None
    #: where more of the positions' smallest changes are small than noise at the reading allows
    #: (:func:`~torchsvs.datasets.noise_ceiling.ceiling_reading`): per axis the most noise
    #: (standard deviation) they allow, NaN on axes they do not contradict; the reading is
    #: motion between reports, ``meas_std_se`` reaches 0 and the noise's range ends at it
    noise_ceiling: list[float] | None = None
    #: the estimators this one was chosen from: ``--estimator auto``'s candidates, or an SVSF
    #: family's and its Kalman twin where the boundary layer's limit did not earn its place
    #: (:func:`~torchsvs.selection.checked_layer`)
    chosen_from: list[str] | None = None
    #: the noise standard deviation per axis as read off the data, where the run took the low
    #: end of its uncertainty instead (:func:`~torchsvs.sample_accuracy.lowered_noise`)
    noise_lowered_from: list[float] | None = None
    #: each position axis's own factor on ``q`` (the least of its SURE curve on the sample),
    #: where the axes of 3-D positions want ``q``'s at least :data:`~torchsvs.fitting.defaults.
    #: AXES_APART` apart (:func:`~torchsvs.fitting.defaults.axes_q`): one ``q`` serves them all
    axis_q: list[float] | None = None
    #: each track at its own noise: the median over its rows of this column's standard
    #: deviations squared, the file's ``meas_var`` their mean (:mod:`torchsvs.fitting.
    #: noise_classes`); the column is read as an extra column of the rows
    noise_column: str | None = None
    #: each track at its own noise read off its own positions, where the file has no column of
    #: it (:func:`~torchsvs.sample_accuracy.with_track_noise`): ``[μ, τ]``, the mean and the
    #: between-track spread of the tracks' ``log σ`` over the file's, that each track's
    #: reading is shrunk with (:func:`~torchsvs.datasets.track_noise.shrunk_ratios`)
    track_noise: list[float] | None = None
    #: where the noise was given and is above what the data show (a bound given as σ), the
    #: noise per axis read off them (:func:`~torchsvs.fitting.defaults.checked_given_noise`)
    noise_above_data: list[float] | None = None
    #: where the noise was given and is well below what the data show (half the sensor's σ,
    #: or motion the model reads as noise), the noise per axis read off them (the same check)
    noise_below_data: list[float] | None = None
    #: each track its own ``q`` (the file's times a factor its SURE picks, shrunk toward the
    #: file's: :func:`~torchsvs.fitting.noise.track_q_factors`), where ``q`` is not given
    track_q: bool = True
    #: the file's SURE curve the tracks' own ``q`` are chosen against (of the Kalman smoother,
    #: or for :data:`FILTERS` the filter, at ``q`` times
    #: :data:`~torchsvs.fitting.noise.Q_FACTORS`); None: one ``q`` for every track
    q_curve: list[float] | None = None
    #: the sample's tracks jump to another path between two reports (two tracks' ids swapped):
    #: every block's tracks are split at such breaks (:mod:`torchsvs.datasets.breaks`)
    track_breaks: bool = False
    #: the tracks' kinds of motion and each kind's curve, which a track's own ``q`` is shrunk
    #: toward (:meth:`~torchsvs.fitting.noise.QCurves.by_kind`); None: toward ``q_curve``
    q_kinds: list[list[float]] | None = None
    #: ``q_curve`` and each track's (or step's) ``q`` reach below
    #: :data:`~torchsvs.fitting.noise.Q_FACTORS` (:func:`~torchsvs.fitting.noise.q_factors`):
    #: set where the sample's still targets want less (:func:`~torchsvs.fitting.defaults.
    #: with_q_curve`)
    q_low: bool = False
    #: the Kalman smoother's ``q`` chosen per step, by SURE over a window of this many steps
    #: around each (:mod:`torchsvs.fitting.q_windows`), where the sample's SURE found it below
    #: each track's own ``q``; None: each track's own (with ``q_curve``). Read by the Kalman
    #: smoother (``ks``) alone: a filter's estimate may not look ahead.
    q_window: int | None = None
    #: let SURE choose a window of ``q`` for the Kalman smoother (``q_window``) where it finds
    #: one better than each track's own ``q``; False: each track's own (``--no-step-q``)
    step_q: bool = True
    #: set isolated outliers aside before estimating (treated as missing, flagged in the
    #: output's ``outlier`` column): :mod:`torchsvs.fitting.outliers`
    outliers: bool = True
    #: the ``q`` of the Kalman smoother that judges outliers (read off the data with them set
    #: aside); None until :func:`~torchsvs.fitting.defaults.screened`
    outlier_q: float | None = None
    #: a second estimator's complete settings whose estimates are blended with this one's
    #: (``--estimator auto`` where SURE finds the blend surely lower: :mod:`torchsvs.blending`);
    #: a dict (as saved) is read back as settings
    blend: Settings | None = None
    #: the weight of ``blend``'s estimates, in (0, 1): ``(1 − w) x̂ + w x̂_blend``
    blend_weight: float = 0.0

    def __post_init__(self) -> None:
        if isinstance(self.blend, dict):  # as asdict (a --save file, a summary) holds it
            self.blend = Settings(**self.blend)
        if self.blend is not None:
            if self.blend.blend is not None:
                raise ValueError("blend: expected the settings of one estimator, not a blend")
            if not 0.0 < self.blend_weight < 1.0:
                raise ValueError(
                    f"blend_weight: expected a weight in (0, 1), got {self.blend_weight!r}"
                )
            if self.blend.meas_var != self.meas_var:
                raise ValueError(
                    "blend: expected the same meas_var as the settings it blends with (SURE "
                    f"pairs them at one noise), got {self.blend.meas_var!r} and "
                    f"{self.meas_var!r}"
                )
        if self.estimator not in ESTIMATORS:
            raise ValueError(
                f"estimator: expected one of {sorted(ESTIMATORS)}, got {self.estimator!r}"
            )
        least = 0 if self.estimator == "imm" else 1  # the IMM's lag 0: its filter
        if self.lag is not None and (
            isinstance(self.lag, bool) or not isinstance(self.lag, int) or self.lag < least
        ):
            raise ValueError(
                f"lag: expected an integer >= {least}"
                + ("" if least else " (0 for imm: its filter)")
                + f", got {self.lag!r}"
            )
        if self.lag is not None and self.estimator not in LAGGED:
            raise ValueError(
                f"lag: {self.estimator} is a filter; a lag applies to "
                f"{', '.join(LAGGED)} (got lag={self.lag})"
            )
        if not 0.0 <= self.gamma < 1.0:
            raise ValueError(f"gamma: expected a value in [0, 1), got {self.gamma!r}")
        if self.q_window is not None and (
            isinstance(self.q_window, bool)
            or not isinstance(self.q_window, int)
            or self.q_window < 3
            or self.q_window % 2 == 0
        ):
            raise ValueError(
                f"q_window: expected an odd number of steps >= 3, got {self.q_window!r}"
            )
        if self.q is not None and not self.q > 0:
            raise ValueError(f"q: expected a number > 0, got {self.q!r}")
        if self.outlier_q is not None and not self.outlier_q > 0:
            raise ValueError(f"outlier_q: expected a number > 0, got {self.outlier_q!r}")
        for name in ("meas_var", "psi"):  # (lists: one per axis, or a layer's widths)
            value = getattr(self, name)
            if value is not None and (
                isinstance(value, (str, bytes)) or not hasattr(value, "__len__") or not len(value)
            ):
                raise ValueError(
                    f"{name}: expected a list of numbers > 0 (one per axis), got {value!r}"
                )
        if self.meas_var is not None and not all(v > 0 for v in self.meas_var):
            raise ValueError(f"meas_var: expected variances > 0, got {self.meas_var!r}")
        if self.psi is not None and not all(p > 0 for p in self.psi):
            raise ValueError(f"psi: expected widths > 0, got {self.psi!r}")
        for name in ("turn_q", "turn_rate_q", "turn_rate_std"):
            value = getattr(self, name)
            if value is not None and not value > 0:
                raise ValueError(f"{name}: expected a number > 0, got {value!r}")
        if self.estimator == "svstps" and not self.velocity:
            # The H⁺ mode never corrects the velocity; the RTS pass over it carries the prior's
            # velocity error into the positions at any lag (6.8x the raw measurements at lag 1
            # on recorded airliners, experiments.recorded_tracks); the SVSS at lag 1 stays
            # below them (HPLUS_LAG).
            raise ValueError(
                "estimator: svstps with velocity=False (--no-velocity: the H⁺ mode, which never "
                "corrects the velocity) diverges on position-only tracks; use svstps without "
                "--no-velocity, or svss --no-velocity (lag 1)"
            )
        if not 0.0 <= self.switch_prob < 1.0:
            raise ValueError(f"switch_prob: expected a value in [0, 1), got {self.switch_prob!r}")

    @property
    def name(self) -> str:
        """The estimator's name, or a blend's ``first+second``."""
        if self.blend is None:
            return self.estimator
        return f"{self.estimator}+{self.blend.estimator}"

    @property
    def as_twin(self) -> bool:
        """Whether an SVSF-family estimator runs as its Kalman twin (``chosen_from`` is the
        family's name and the twin, :data:`KALMAN_TWINS`), not as ``--estimator auto``'s
        choice."""
        chosen = self.chosen_from
        return chosen is not None and len(chosen) == 2 and KALMAN_TWINS.get(chosen[0]) == chosen[1]

    @property
    def reading_is_motion(self) -> bool:
        """Whether the noise read off the data is contradicted as motion between reports, by
        the second differences two reports apart (``noise_lag``) or by the smallest changes
        (``noise_ceiling``, :func:`~torchsvs.datasets.noise_lags.motion_checked`)."""
        return self.reading_is_motion_on(None)

    def reading_is_motion_on(self, axes: Sequence[int] | None) -> bool:
        """:attr:`reading_is_motion` on some of the position's ``axes`` (None: any)."""
        if self.noise != "data":
            return False
        for per_axis in (self.noise_lag, self.noise_ceiling):
            if per_axis is not None:
                picked = per_axis if axes is None else [per_axis[j] for j in axes]
                if any(v is not None and v == v for v in picked):
                    return True
        return False

    @property
    def exact_divergence(self) -> bool:
        """Whether the error estimate's divergence is exact (the linear Kalman filter or
        smoother alone: the same at every probe, :mod:`torchsvs.accuracy`); a blend's is not."""
        return self.blend is None and self.estimator in KALMAN

    @property
    def blended(self) -> tuple[Settings, Settings] | None:
        """The two estimators' settings of a blend (this one's without the blend first), or
        None."""
        if self.blend is None:
            return None
        return replace(self, blend=None, blend_weight=0.0), self.blend

    @property
    def own_noise(self) -> bool:
        """Whether each track runs at its own measurement noise: given per row
        (``noise_column``) or read off each track (``track_noise``),
        :mod:`torchsvs.fitting.noise_classes`."""
        return self.noise_column is not None or self.track_noise is not None

    @property
    def screens(self) -> bool:
        """Whether isolated outliers are set aside before estimating (``outliers``, with the
        ``outlier_q`` read off the data): :func:`~torchsvs.estimating.estimate_group`."""
        return self.outliers and self.outlier_q is not None

    @property
    def smoother_lag(self) -> int | None:
        if self.lag is not None:
            return self.lag
        if not self.velocity and self.estimator in ("svss", "svstps"):
            return HPLUS_LAG
        return DEFAULT_LAG.get(self.estimator)


def rule_of_thumb_psi(axes: int, velocity: bool = True, estimator: str = "svsf") -> list[float]:
    """ψ of the SVSF family of ``track``, one per axis, in units of each step's own noise (so
    neither the noise level nor the interval enters it):

    * ``velocity`` (default): the limit of the variable boundary layer
      (:class:`~torchsvs.filters.VariableBoundarySVSF`), :data:`PSI_LIMIT_IN_SIGMAS` innovation
      standard deviations for a filter, :data:`PSI_SMOOTHER_LIMIT_IN_SIGMAS` for the smoothers
      over it (``svss``, ``svstps``): the Kalman gain inside, the SVSF's beyond.
    * the ``H⁺`` mode: :data:`PSI_IN_SIGMAS` measurement noise standard deviations
      (``psi_units="noise"``). Chen et al. 2020 use ψ = 800 m for 200 m noise (Sec. 4.1) and
      500 m / 600 m/s for 100 m noise with finite-difference velocities (Sec. 4.2, whose noise
      is √2·100 m/s at T = 1 s): four to five standard deviations.
    """
    if not velocity:
        return [PSI_IN_SIGMAS] * axes
    smoother = estimator in ("svss", "svstps")
    return [PSI_SMOOTHER_LIMIT_IN_SIGMAS if smoother else PSI_LIMIT_IN_SIGMAS] * axes


#: The settings the noise read off the data fills in (:func:`~torchsvs.fitting.noise_read.
#: with_noise_read`, and each track's own, :func:`~torchsvs.sample_accuracy.with_track_noise`):
#: what a run carries from the reading it settles on.
NOISE_READ = (
    "meas_var",
    "noise",
    "meas_std_se",
    "noise_spread",
    "noise_within",
    "noise_lag",
    "noise_ceiling",
    "track_noise",
)


def make_model(
    settings: Settings, learn_q: bool = False, learn_r: bool = False
) -> ConstantVelocity:
    """The nearly-constant-velocity model of the settings (``meas_var`` and ``q`` must be set)."""
    if settings.meas_var is None or settings.q is None:
        raise ValueError("settings: meas_var and q must be known before the model is built")
    return ConstantVelocity(
        ndim=len(settings.meas_var),
        dt=settings.interval,
        q=settings.q,
        r=list(settings.meas_var),
        learn_q=learn_q,
        learn_r=learn_r,
    )


class Blend(nn.Module):
    """Two estimators whose estimates are blended, ``(1 − w) x̂₁ + w x̂₂``: what ``track``
    runs for settings with a ``blend`` (:func:`torchsvs.estimating.estimate_group` runs each
    and blends them, :mod:`torchsvs.blending`; a container, not called itself)."""

    def __init__(self, first: nn.Module, second: nn.Module, weight: float) -> None:
        super().__init__()
        self.first, self.second, self.weight = first, second, weight

    def forward(self, *args: Any, **kwargs: Any) -> Any:
        raise TypeError(
            "Blend: its estimators run apart and are blended by torchsvs.estimating.estimate_group"
        )


def make_estimator(settings: Settings, model: ConstantVelocity) -> Estimator | Blend:
    """The estimator ``settings.estimator`` on ``model`` (the IMM's turn settings must be set;
    its turn noises are learnable when ``model``'s ``q`` is); with a ``blend``, both (the
    second on its own model) in a :class:`Blend`."""
    pair = settings.blended
    if pair is not None:
        first, second = pair
        return Blend(
            make_estimator(first, model),
            make_estimator(second, make_model(second)),
            settings.blend_weight,
        )
    name = settings.estimator
    if name == "auto":
        raise ValueError(
            "estimator: 'auto' is a choice among estimators, made on data "
            "(torchsvs.selection.choose_estimator), not an estimator to build"
        )
    if name == "imm":
        if settings.turn_rate_q is None or settings.turn_rate_std is None:
            raise ValueError(
                "settings: turn_rate_q and turn_rate_std must be known before the IMM is built"
            )
        if model.ndim not in (2, 3):
            raise ValueError(
                f"estimator: imm turns in the horizontal plane of 2 or 3 position axes, got "
                f"{model.ndim}"
            )
        p = settings.switch_prob
        turn = TurnIMM(
            model,
            turn_q=settings.turn_q,
            turn_rate_q=settings.turn_rate_q,
            turn_rate_std=settings.turn_rate_std,
            transition=[[1.0 - p, p], [p, 1.0 - p]],
        )
        lag = settings.smoother_lag
        return turn if lag == 0 else TurnIMMSmoother(turn, lag)
    if name in KALMAN:
        kf = KalmanFilter(model)
        return kf if name == "kf" else RTSSmoother(kf, lag=settings.smoother_lag)
    if name == "ekf":
        return ExtendedKalmanFilter(model)
    if name == "ukf":
        return UnscentedKalmanFilter(model)
    if name == "rstkf":
        # Swapped shapes: the derived ones take a turn's innovations for measurement outliers
        # and lose the target (7x raw on airliners at their own report times; robust.py).
        return RobustStudentTKalmanFilter(model, scale_shapes="swapped")
    if name == "pf":
        # The optimal proposal, regularised: the bootstrap loses tracks at long scan intervals
        # and in maneuvers the data's q misses (ParticleFilter's docstring).
        return ParticleFilter(
            model, num_particles=settings.particles, proposal="optimal", regularize=True
        )
    assert settings.meas_var is not None
    # ψ in units of each step's own noise (rule_of_thumb_psi), one per axis.
    psi = settings.psi or rule_of_thumb_psi(len(settings.meas_var), settings.velocity, name)
    if name == "spvsf":
        return SPVSF(
            model,
            psi=psi,
            gamma=settings.gamma,
            num_particles=settings.particles,
            artificial=None,
            variable_boundary=settings.velocity,
            psi_units="absolute" if settings.velocity else "noise",
            regularize=True,
        )
    svsf: SVSF
    if settings.velocity:
        svsf = VariableBoundarySVSF(model, psi=psi, gamma=settings.gamma)
    else:
        svsf = SVSF(model, psi=psi, gamma=settings.gamma, artificial=None, psi_units="noise")
    if name == "svsf":
        return svsf
    if name == "svss":
        return SVSS(svsf, lag=settings.smoother_lag)
    return RTSSmoother(svsf, lag=settings.smoother_lag)


def short(value: Any) -> str:
    """A setting's value as the run's lines show it (floats to 4 digits)."""
    if isinstance(value, float):
        return f"{value:.4g}"
    if isinstance(value, list):
        return "[" + ", ".join(short(v) for v in value) + "]"
    return str(value)

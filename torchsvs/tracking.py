"""Tracking recorded files: estimators by name, their settings from the data, and the loop
behind ``torchsvs track``.

Every estimator runs on a nearly-constant-velocity model (:class:`~torchsvs.models.
ConstantVelocity`) of the file's axes; the IMM (``imm``) mixes it with a coordinated turn
(:class:`~torchsvs.filters.TurnIMM`) and writes the same constant-velocity state. What the model
needs and the user did not give comes from the data: the measurement noise (and its standard
error) from :func:`~torchsvs.datasets.estimate_noise`, ``q`` as the Kalman smoother's (for a
filter, the Kalman filter's) by its exact SURE (:func:`torchsvs.training.noise.smoother_q`),
the priors from two-point differencing,
the SVSF's boundary layer from the rule of thumb :func:`rule_of_thumb_psi`, and the IMM's mode
noises from :func:`turn_settings`. ``--fit`` then tunes them on the file itself
(:func:`torchsvs.training.tuning.self_tune`); ``auto`` fits several and keeps the one of the
lowest estimated error (:mod:`torchsvs.training.selection`). Every run estimates its own error
without truth (:mod:`torchsvs.accuracy`) and warns where it is not clearly below the
measurements'.
"""

from __future__ import annotations

import contextlib
import math
import time
from collections import Counter
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any, NamedTuple, TypeVar

import numpy as np
import torch
from torch import Tensor, nn

from torchsvs.accuracy import Accuracy, RiskTerms, RiskTotals, risk_terms
from torchsvs.accuracy import accuracy as accuracy_of
from torchsvs.datasets import (
    Columns,
    EstimateWriter,
    RecordedTracks,
    RowReport,
    TrackBlock,
    TrackSteps,
    estimate_noise,
    estimate_table,
    noise_spread,
    track_blocks,
    with_prior,
)
from torchsvs.datasets.files import check_output, flat_steps, short_track_notes
from torchsvs.estimator import Estimator
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
from torchsvs.filters.particle import DEGENERATE_SHARE, degenerate_share
from torchsvs.filters.turn_imm import TurnIMM
from torchsvs.models import ConstantVelocity
from torchsvs.smoothers import SVSS, RTSSmoother

Item = TypeVar("Item")

#: Estimator names of ``torchsvs track --estimator`` and what they are.
ESTIMATORS = {
    "auto": "the lowest estimated error of ks, svss (svstps with --no-velocity), imm (small "
    "files), each tuned on the file without truth (torchsvs.training.selection)",
    "kf": "Kalman filter",
    "ks": "Kalman smoother (RTS; fixed interval unless --lag)",
    "svsf": "smooth variable structure filter",
    "svss": "smooth variable structure smoother (fixed lag)",
    "svstps": "two-pass smoother: RTS over the SVSF (fixed lag)",
    "ekf": "extended Kalman filter (the KF on this linear model)",
    "ukf": "unscented Kalman filter (the KF on this linear model)",
    "rstkf": "robust Student's t Kalman filter",
    "pf": "SIR particle filter",
    "spvsf": "smooth particle variable structure filter",
    "imm": "IMM of a KF on constant velocity and an EKF on a coordinated turn (horizontal)",
}
#: Lag of each smoother when none is given (``None``: fixed interval).
DEFAULT_LAG: dict[str, int | None] = {"ks": None, "svss": 5, "svstps": 5}
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
#: The IMM's CV mode's ``q`` as a fraction of the data's (:func:`turn_settings`).
IMM_QUIET = 0.03
#: Share of a particle filter's steps with a degenerate sample above which a run warns.
DEGENERATE_WARNING = 0.3
#: Between-track spread of the noise read off the data (relative) above which a run warns:
#: 0.27 on gliders and survey aircraft at 6-33 s reports, at most 0.12 on the benchmark's other
#: recorded kinds (``experiments/results/recorded_tracks.md``).
NOISE_SPREAD_WARNING = 0.2
#: Per-track error estimates a run keeps beyond this many tracks: the worst this many.
TRACKS_KEPT = 10_000
#: Seed offset of the truth-free error estimate's probes (apart from the particles' seeds).
PROBE_SEED = 1 << 20
#: The IMM's turn-rate scale in units of ``√(q/T) / v̄`` (:func:`turn_settings`).
TURN_RATE_SCALE = 0.3


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
    #: likelihood); None until :func:`complete_settings`
    noise: str | None = None
    #: standard error of the noise standard deviation per axis, where it was read off the data
    meas_std_se: list[float] | None = None
    #: where the noise was read off the data: how much the reading differs between tracks
    #: beyond their own uncertainty (a relative spread, :func:`~torchsvs.datasets.noise_spread`;
    #: also in ``meas_std_se``)
    noise_spread: float | None = None
    #: ``--estimator auto``: the candidates this estimator was chosen from
    chosen_from: list[str] | None = None
    #: each track its own ``q`` (the file's times a factor its SURE picks, shrunk toward the
    #: file's: :func:`~torchsvs.training.noise.track_q_factors`), where ``q`` is not given
    track_q: bool = True
    #: the file's SURE curve the tracks' own ``q`` are chosen against (of the Kalman smoother,
    #: or for :data:`FILTERS` the filter, at ``q`` times
    #: :data:`~torchsvs.training.noise.Q_FACTORS`); None: one ``q`` for every track
    q_curve: list[float] | None = None

    def __post_init__(self) -> None:
        if self.estimator not in ESTIMATORS:
            raise ValueError(
                f"estimator: expected one of {sorted(ESTIMATORS)}, got {self.estimator!r}"
            )
        if self.lag is not None and (
            isinstance(self.lag, bool) or not isinstance(self.lag, int) or self.lag < 1
        ):
            raise ValueError(f"lag: expected an integer >= 1, got {self.lag!r}")
        if not 0.0 <= self.gamma < 1.0:
            raise ValueError(f"gamma: expected a value in [0, 1), got {self.gamma!r}")
        if self.q is not None and not self.q > 0:
            raise ValueError(f"q: expected a number > 0, got {self.q!r}")
        if self.psi is not None and not all(p > 0 for p in self.psi):
            raise ValueError(f"psi: expected widths > 0, got {self.psi!r}")
        for name in ("turn_q", "turn_rate_q", "turn_rate_std"):
            value = getattr(self, name)
            if value is not None and not value > 0:
                raise ValueError(f"{name}: expected a number > 0, got {value!r}")
        if not 0.0 <= self.switch_prob < 1.0:
            raise ValueError(f"switch_prob: expected a value in [0, 1), got {self.switch_prob!r}")

    @property
    def smoother_lag(self) -> int | None:
        return self.lag if self.lag is not None else DEFAULT_LAG.get(self.estimator)


def rule_of_thumb_psi(axes: int, velocity: bool = True) -> list[float]:
    """ψ of the SVSF family of ``track``, one per axis, in units of each step's own noise (so
    neither the noise level nor the interval enters it):

    * ``velocity`` (default): the limit of the variable boundary layer
      (:class:`~torchsvs.filters.VariableBoundarySVSF`), :data:`PSI_LIMIT_IN_SIGMAS` innovation
      standard deviations: the Kalman gain inside, the SVSF's beyond.
    * the ``H⁺`` mode: :data:`PSI_IN_SIGMAS` measurement noise standard deviations
      (``psi_units="noise"``). Chen et al. 2020 use ψ = 800 m for 200 m noise (Sec. 4.1) and
      500 m / 600 m/s for 100 m noise with finite-difference velocities (Sec. 4.2, whose noise
      is √2·100 m/s at T = 1 s): four to five standard deviations.
    """
    return [PSI_LIMIT_IN_SIGMAS if velocity else PSI_IN_SIGMAS] * axes


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


def make_estimator(settings: Settings, model: ConstantVelocity) -> Estimator:
    """The estimator ``settings.estimator`` on ``model`` (the IMM's turn settings must be set;
    its turn noises are learnable when ``model``'s ``q`` is)."""
    name = settings.estimator
    if name == "auto":
        raise ValueError(
            "estimator: 'auto' is a choice among estimators, made on data "
            "(torchsvs.training.selection.choose_estimator), not an estimator to build"
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
        return TurnIMM(
            model,
            turn_q=settings.turn_q,
            turn_rate_q=settings.turn_rate_q,
            turn_rate_std=settings.turn_rate_std,
            transition=[[1.0 - p, p], [p, 1.0 - p]],
        )
    if name in ("kf", "ks"):
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
    psi = settings.psi or rule_of_thumb_psi(len(settings.meas_var), settings.velocity)
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


def typical_speed(tracks: RecordedTracks) -> float:
    """The median horizontal speed of the tracks (their first two axes) between successive
    observed positions (noise included), or 0 where no two successive positions are
    observed."""
    z = tracks.z[..., :2].to(torch.float64)
    step = (z[:, 1:] - z[:, :-1]).norm(dim=-1) / tracks.dt[:, 1:].to(torch.float64)
    step = step[torch.isfinite(step)]
    return float(step.median()) if step.numel() else 0.0


def imm_base_q(tracks: RecordedTracks, meas_var: Sequence[float]) -> float:
    """The ``q`` the IMM's mode noises are derived from (:func:`turn_settings`): the Kalman
    filter's SURE ``q`` of the horizontal axes. Short differences
    (:func:`~torchsvs.datasets.estimate_noise`'s ``q``) read circling gliders at 10-30 s as a
    quiet CV target and left the IMM at 1.9× raw; the turn is horizontal, and a calm height
    would dilute its scale."""
    horizontal = replace(tracks, z=tracks.z[..., :2])
    return _sure_q(horizontal, list(meas_var)[:2], "kf")


def turn_settings(
    q: float,
    meas_var: Sequence[float],
    interval: float,
    speed: float,
    quiet: float = IMM_QUIET,
    rate_scale: float = TURN_RATE_SCALE,
) -> dict[str, float]:
    r"""The IMM's mode noises from the data's ``q`` (the spectral density of a single CV model,
    which counts the maneuvers as noise: :func:`complete_settings` passes the Kalman filter's
    SURE ``q``), the measurement noise, the typical interval ``T``
    and the typical horizontal speed :math:`\bar v` (:func:`typical_speed`):

    * CV mode: ``q_CV = quiet · q`` (:data:`IMM_QUIET`): quiet, the turns go to the CT mode;
    * CT mode: white acceleration variance ``turn_q = q / T`` (the velocity noise per step of
      the single CV model) and a turn-rate scale :math:`\omega_s = s\,\sqrt{q/T}/\bar v`
      with ``s = rate_scale`` (:data:`TURN_RATE_SCALE`): :math:`\sqrt{q/T}/\bar v` is the
      turn rate whose centripetal acceleration at the typical speed is the CV model's
      acceleration noise over a step. :math:`\omega_s` is the prior standard deviation of
      the turn rate and its standard deviation of change per typical step
      (``turn_rate_q = (ω_s / T)²``).

    For a three-axis file ``q`` is read off the horizontal axes (the turn is horizontal; a calm
    height would dilute the one ``q`` of all three). The speed is floored at the speed the
    measurement noise alone shows between two steps
    (:math:`\sqrt{2r}/T`), so still or slow targets get a finite, small turn rate. The factors
    were chosen on the training half of the recorded calibration flights at σ = 50, 100 and
    200 m (``experiments/results/real_flights.md``, IMM section: a grid of CV shares 0.01-1
    and turn-rate scales 0.1-1). With :func:`imm_base_q` as the base (the study first ran on
    the ``q`` of short differences, to the same choice) the defaults are within 0.5% of the
    grid's best position RMSE at every level, and a quieter CV mode is better down to 0.03
    there (and on simulated turns); a turn-rate scale of 1 let the turn mode's turn rate
    wander to aliasing values (ωT of several radians between scans) on some flights, with
    velocity errors of thousands of m/s.
    """
    r = sum(meas_var[:2]) / len(meas_var[:2])
    speed = max(speed, math.sqrt(2.0 * r) / interval)
    scale = rate_scale * math.sqrt(q / interval) / speed
    return {
        "q": quiet * q,
        "turn_q": q / interval,
        "turn_rate_q": (scale / interval) ** 2,
        "turn_rate_std": scale,
    }


def complete_settings(settings: Settings, tracks: RecordedTracks) -> Settings:
    """Fills what the settings leave open from the data: noise levels and the typical interval
    (and the IMM's mode noises, :func:`turn_settings`)."""
    source = settings.noise or ("given" if settings.meas_var is not None else "data")
    meas_std_se, spread = settings.meas_std_se, settings.noise_spread
    interval = float(tracks.dt[tracks.mask].median()) if len(tracks) else 1.0
    meas_var, q = settings.meas_var, settings.q
    imm = settings.estimator == "imm"
    turn_open = imm and None in (settings.turn_q, settings.turn_rate_q, settings.turn_rate_std)
    if meas_var is None:
        try:
            noise = estimate_noise(tracks.z, tracks.dt)
        except ValueError as err:
            raise ValueError(
                "meas_std: too few observed positions to read the measurement noise off the "
                "data; give it (--meas-std) and the process noise (--q)"
            ) from err
        meas_var = noise.meas_var.double().tolist()
        spread = noise_spread(tracks.z, tracks.dt)
        meas_std_se = _noise_standard_error(noise, meas_var, spread)
    m = tracks.z.shape[-1]
    if len(meas_var) == 1 and m > 1:
        meas_var = list(meas_var) * m
    if len(meas_var) != m:
        raise ValueError(f"meas_std: expected one value or one per axis ({m}), got {len(meas_var)}")
    data_q = None
    if q is None or turn_open:
        try:
            data_q = (
                imm_base_q(tracks, meas_var)
                if imm
                else _sure_q(tracks, meas_var, settings.estimator)
            )
        except ValueError:  # too little data to say: the measurement noise over one step
            data_q = sum(meas_var) / len(meas_var) / interval**3
    if q is None and not imm:
        q = data_q
    turn_q, turn_rate_q, turn_rate_std = (
        settings.turn_q,
        settings.turn_rate_q,
        settings.turn_rate_std,
    )
    if imm:
        if m not in (2, 3):
            raise ValueError(
                f"estimator: imm turns in the horizontal plane of 2 or 3 position axes, got {m}"
            )
        if data_q is not None:
            derived = turn_settings(data_q, meas_var, interval, typical_speed(tracks))
            q = derived["q"] if q is None else q
            turn_q = turn_q or derived["turn_q"]
            turn_rate_q = turn_rate_q or derived["turn_rate_q"]
            turn_rate_std = turn_rate_std or derived["turn_rate_std"]
    psi = settings.psi
    if psi is None and settings.estimator in ("svsf", "svss", "svstps", "spvsf"):
        psi = rule_of_thumb_psi(m, settings.velocity)
    elif psi is not None and len(psi) == 1 and m > 1:
        psi = list(psi) * m  # one value for every axis, as --psi's help says
    assert q is not None  # (an open q sent the IMM through the data too)
    if meas_std_se is not None and len(meas_std_se) == 1 and m > 1:
        meas_std_se = list(meas_std_se) * m
    return replace(
        settings,
        meas_var=[float(v) for v in meas_var],
        noise=source,
        meas_std_se=meas_std_se,
        noise_spread=spread,
        q=float(q),
        interval=interval,
        psi=psi,
        turn_q=turn_q,
        turn_rate_q=turn_rate_q,
        turn_rate_std=turn_rate_std,
    )


#: Estimators whose output is a filter's (each step from the past alone): their q is the
#: Kalman filter's, the others' the Kalman smoother's (:func:`_sure_q`).
FILTERS = ("kf", "ekf", "ukf", "rstkf", "pf", "spvsf", "svsf")


def _sure_q(tracks: RecordedTracks, meas_var: Sequence[float], estimator: str) -> float:
    """The q a Kalman smoother (or, for :data:`FILTERS`, a Kalman filter) serves these tracks
    with (:func:`torchsvs.training.noise.smoother_q`: its exact SURE, the noise fixed): the
    motion that short differences show (``estimate_noise``'s q) is no guide at long scans or
    for slow targets."""
    from torchsvs.training.noise import smoother_q

    r = torch.tensor(meas_var, dtype=torch.float64)
    return smoother_q(tracks.z, tracks.dt, r, smoothed=estimator not in FILTERS).q


def _noise_standard_error(
    noise: Any, meas_var: Sequence[float], spread: float | None
) -> list[float] | None:
    """The standard error of the noise standard deviation per axis that
    :func:`~torchsvs.datasets.estimate_noise` reports, if it does, with the between-track
    spread (:func:`~torchsvs.datasets.noise_spread`) added in quadrature: where one noise level
    does not fit every track, the pooled reading is that uncertain, whatever its jackknife."""
    se = getattr(noise, "meas_std_se", None)
    if se is None:
        return None
    extra = [(spread or 0.0) * v**0.5 for v in meas_var]
    return [
        math.hypot(float(v), e) for v, e in zip(torch.as_tensor(se).reshape(-1), extra, strict=True)
    ]


def meas_var_range(settings: Settings) -> tuple[list[float], list[float]] | None:
    """The measurement variance two standard errors below and above the settings' own, where
    the noise was read off the data with a standard error (else None)."""
    if settings.noise == "given" or settings.meas_var is None or settings.meas_std_se is None:
        return None
    std = [v**0.5 for v in settings.meas_var]
    low = [max(s - 2 * e, 0.0) ** 2 for s, e in zip(std, settings.meas_std_se, strict=True)]
    high = [(s + 2 * e) ** 2 for s, e in zip(std, settings.meas_std_se, strict=True)]
    return low, high


def sample_accuracy(settings: Settings, tracks: RecordedTracks) -> Accuracy:
    """The truth-free error estimate (:mod:`torchsvs.accuracy`) of the estimator of complete
    ``settings`` on padded ``tracks`` (run as ``torchsvs track`` runs it, in float64)."""
    assert settings.meas_var is not None
    estimator = make_estimator(settings, make_model(settings)).double()
    moved, offset = centred(tracks.to(torch.float64))
    batch = GroupBatch(0, np.arange(len(tracks)), moved, offset)
    meas_std = torch.tensor(settings.meas_var, dtype=torch.float64).sqrt()
    part = estimate_group(estimator, batch, meas_std, risk=True)
    assert part.risk is not None
    return accuracy_of(
        part.risk,
        settings.meas_var,
        noise_estimated=settings.noise != "given",
        meas_var_range=meas_var_range(settings),
    )


def centred(tracks: RecordedTracks) -> tuple[RecordedTracks, Tensor]:
    """The tracks moved so each starts near 0 (float32 keeps its resolution on large
    coordinates), and the offsets ``[B, m]`` to add back."""
    observed = ~torch.isnan(tracks.z)
    first = observed.to(torch.int64).argmax(dim=1, keepdim=True)  # [B, 1, m]
    offset = tracks.z.nan_to_num(0.0).gather(1, first).squeeze(1)
    return replace(tracks, z=tracks.z - offset.unsqueeze(1)), offset


def run_result(
    estimator: nn.Module, tracks: RecordedTracks, generator: torch.Generator | None = None
) -> Any:
    """An estimator's whole result on tracks with priors (no gradients)."""
    assert tracks.x0 is not None and tracks.P0 is not None
    kwargs: dict[str, Any] = {"dt": tracks.dt}
    if isinstance(estimator, ParticleFilter):
        kwargs["generator"] = (
            generator if generator is not None else torch.Generator().manual_seed(0)
        )
    with torch.no_grad():
        return estimator(tracks.z, tracks.x0, tracks.P0, **kwargs)


def run_estimator(
    estimator: nn.Module, tracks: RecordedTracks, generator: torch.Generator | None = None
) -> tuple[Tensor, Tensor]:
    """Mean ``[B, T, 2m]`` and covariance of an estimator on tracks with priors (no gradients)."""
    out = run_result(estimator, tracks, generator)
    return out.mean, out.cov


class GroupBatch(NamedTuple):
    """One estimator call of ``torchsvs track``: a group of a block's tracks
    (:meth:`~torchsvs.datasets.TrackSteps.batches`), padded and moved to start near 0."""

    position: int  #: the group's position among the block's groups (seeds its random draws)
    group: np.ndarray  #: [B] int64 the group's tracks among the block's
    tracks: RecordedTracks  #: z [B, T, m] in the computation's dtype, priors not yet set
    offset: Tensor  #: [B, m] float64 what :func:`centred` took off, to add back


class StepEstimates(NamedTuple):
    """A group's estimates at the block's flat steps, in float64: what a process hands back."""

    position: int  #: the group's position among the block's groups
    group: np.ndarray  #: [B] int64 the group's tracks among the block's
    steps: np.ndarray  #: [s] int64 the block's flat step of each estimate
    mean: np.ndarray  #: [s, 2m]
    cov: np.ndarray | None  #: [s, 2m, 2m], or None when not asked for
    never_observed: np.ndarray  #: [B, m] bool
    notes: dict[str, int]  #: :func:`~torchsvs.datasets.files.short_track_notes` of the group
    #: SURE's sums (:mod:`torchsvs.accuracy`), chunks' ``track`` the block's track, or None
    risk: RiskTerms | None = None
    #: [B] each track's factor on the settings' ``q`` (:func:`track_q_factors`), or None
    q_factor: np.ndarray | None = None

    @classmethod
    def merge(cls, parts: Sequence[StepEstimates], m: int) -> StepEstimates:
        """One group's estimates from those of parts of its tracks (same position)."""
        if len(parts) == 1:
            return parts[0]
        notes: Counter[str] = Counter()
        for part in parts:
            notes.update(part.notes)
        covs = [p.cov for p in parts]
        risks = [p.risk for p in parts if p.risk is not None]
        return cls(
            parts[0].position,
            np.concatenate([p.group for p in parts]),
            np.concatenate([p.steps for p in parts]),
            np.concatenate([p.mean for p in parts]),
            None if any(c is None for c in covs) else np.concatenate(covs),  # type: ignore[arg-type]
            np.concatenate([p.never_observed for p in parts]),
            dict(notes),
            RiskTerms.concat(risks, m) if len(risks) == len(parts) else None,
            np.concatenate([p.q_factor for p in parts if p.q_factor is not None]),
        )


def group_batch(
    steps: TrackSteps, group: np.ndarray, position: int, dtype: torch.dtype
) -> GroupBatch:
    """The tracks ``group`` (the block's group number ``position``) padded (float64, so the
    offsets are exact), centred, then cast to ``dtype``."""
    tracks, offset = centred(steps.pad(group, torch.float64))
    return GroupBatch(position, group, tracks.to(dtype), offset)


def estimate_group(
    estimator: nn.Module,
    batch: GroupBatch,
    meas_std: Tensor,
    covariance: bool = False,
    risk: bool = True,
    settings: Settings | None = None,
) -> StepEstimates:
    """Priors from ``meas_std [m]`` (:func:`~torchsvs.datasets.with_prior`), the estimator's
    run and the offsets added back. Random draws (particle filters) come from a generator
    seeded with the group's position, so a group's estimates do not depend on which groups ran
    before it, nor in which process. With ``risk``, a second run on probed measurements gives
    the truth-free error estimate's terms (:func:`~torchsvs.accuracy.risk_terms`).

    Where ``settings`` carry the file's SURE curve (``q_curve``), each track runs with its own
    ``q`` (:func:`track_q_factors`): the tracks of one factor together, ``estimator``'s ``q``
    scaled by it for the call (:func:`scaled_q`)."""
    if settings is None or settings.q_curve is None:
        return _estimate_part(estimator, batch, meas_std, covariance, risk)
    factors = track_q_factors(settings, batch.tracks)
    parts = []
    for factor in torch.unique(factors).tolist():
        index = torch.nonzero(factors == factor).flatten()
        part = GroupBatch(
            batch.position,
            batch.group[index.numpy()],
            batch.tracks.subset(index),
            batch.offset[index],
        )
        with scaled_q(estimator, factor):
            found = _estimate_part(estimator, part, meas_std, covariance, risk)
        parts.append(found._replace(q_factor=np.full(len(index), factor)))
    return StepEstimates.merge(parts, len(meas_std))


def track_q_factors(settings: Settings, tracks: RecordedTracks) -> Tensor:
    """``[B]`` each track's factor on ``settings.q`` (:func:`torchsvs.training.noise.
    track_q_factors` against the file's curve ``settings.q_curve``)."""
    from torchsvs.training import noise

    assert settings.q_curve is not None and settings.meas_var is not None
    assert settings.q is not None
    curves = noise.q_curves(
        tracks.z, tracks.dt, settings.meas_var, settings.q, settings.estimator not in FILTERS
    )
    return noise.track_q_factors(curves, settings.q_curve)


@contextlib.contextmanager
def scaled_q(estimator: nn.Module, factor: float) -> Iterator[nn.Module]:
    """The estimator with its motion model's ``q`` times ``factor`` inside the block (then
    restored exactly)."""
    if factor == 1.0:
        yield estimator
        return
    model = estimator.model
    assert isinstance(model, ConstantVelocity), "scaled_q: a constant-velocity model's q"
    raw = model.q.raw  # q is stored as its log (constraints.Positive)
    kept = raw.detach().clone()
    with torch.no_grad():
        raw.add_(math.log(factor))
    try:
        yield estimator
    finally:
        with torch.no_grad():
            raw.copy_(kept)


def _estimate_part(
    estimator: nn.Module,
    batch: GroupBatch,
    meas_std: Tensor,
    covariance: bool = False,
    risk: bool = True,
) -> StepEstimates:
    """:func:`estimate_group` with the estimator as it is."""

    def positions(z: Tensor) -> Any:
        tracks = with_prior(replace(batch.tracks, z=z), meas_std)
        generator = torch.Generator().manual_seed(batch.position)
        return run_result(estimator, tracks, generator)

    tracks = with_prior(batch.tracks, meas_std)
    out = positions(batch.tracks.z)
    mean, cov = out.mean, out.cov
    notes = short_track_notes(tracks)
    if getattr(out, "ess", None) is not None:  # a particle filter: how often it degenerated
        measured = (~torch.isnan(tracks.z)).any(-1).sum(-1)  # [B] steps with a measurement
        notes["particle_steps"] = int(measured.sum())
        low = degenerate_share(out, tracks.z) * measured
        notes["particle_steps_degenerate"] = int(low.sum().round())
    terms = None
    if risk:
        probes = torch.Generator().manual_seed(PROBE_SEED + batch.position)
        terms = risk_terms(
            lambda z: positions(z).mean[..., 0::2], tracks.z, mean[..., 0::2], meas_std, probes
        )
        terms.track = batch.group[terms.track]
    mean = mean.double()
    mean[..., 0::2] += batch.offset.unsqueeze(1)
    target, values, covs = flat_steps(tracks, mean, cov if covariance else None)
    assert tracks.never_observed is not None
    never = tracks.never_observed.numpy()
    return StepEstimates(batch.position, batch.group, target, values, covs, never, notes, terms)


@dataclass
class BlockEstimates:
    """A block's estimates at its flat steps, filled group by group (:meth:`add`)."""

    mean: np.ndarray  #: [S, 2m] NaN until estimated
    cov: np.ndarray | None  #: [S, 2m, 2m]
    never_observed: np.ndarray  #: [K, m] bool
    notes: Counter[str] = field(default_factory=Counter)
    groups: set[int] = field(default_factory=set)  #: positions of the groups added
    risk: list[RiskTerms] = field(default_factory=list)  #: the groups' SURE terms
    q_factors: list[np.ndarray] = field(default_factory=list)  #: the groups' tracks' q factors

    @classmethod
    def empty(cls, steps: TrackSteps, covariance: bool = False) -> BlockEstimates:
        S, m = steps.position.shape
        return cls(
            np.full((S, 2 * m), np.nan),
            np.full((S, 2 * m, 2 * m), np.nan) if covariance else None,
            np.zeros((steps.num_tracks, m), dtype=bool),
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
            self.q_factors.append(part.q_factor)

    def table(self, block: TrackBlock) -> Any:
        """The block's output rows (:func:`~torchsvs.datasets.estimate_table`)."""
        return estimate_table(block, self.mean, self.cov, self.never_observed)


@dataclass
class TrackRun:
    """What ``torchsvs track`` did."""

    report: RowReport = field(default_factory=RowReport)
    settings: Settings | None = None
    seconds: float = 0.0
    estimate_seconds: float = 0.0
    estimate_cpu_seconds: float = 0.0  #: CPU time of this process (rank 0) while estimating
    fit: Any = None  #: the fit's summary (:class:`~torchsvs.training.tuning.FitResult`)
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

    def add_track_errors(self, terms: Sequence[RiskTerms], ids: Sequence[str]) -> None:
        """Adds a block's per-track error estimates (the worst :data:`TRACKS_KEPT` kept)."""
        assert self.settings is not None and self.settings.meas_var is not None
        m = len(self.settings.meas_var)
        rmse, points = RiskTerms.concat(terms, m).per_track(self.settings.meas_var, len(ids))
        for k in np.flatnonzero(points > 0):
            self.track_errors[ids[int(k)]] = (float(rmse[k]), int(points[k]))
        if len(self.track_errors) > 2 * TRACKS_KEPT:
            worst = sorted(self.track_errors.items(), key=lambda kv: -kv[1][0])[:TRACKS_KEPT]
            self.track_errors = dict(worst)

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
            "rows": {"total": self.report.total, "placed": self.report.placed},
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
    the user left open are read off the first block (:func:`complete_settings`); with ``fit``
    the estimator is tuned on the first block's tracks (up to ``fit_options["tracks"]``) without
    truth before anything is written. Each block is estimated in groups of tracks of similar
    length of at most ``max_cells`` padded steps, so memory stays bounded.

    Args:
        source, target: input and output files (``.csv`` or ``.parquet`` each).
        settings: the estimator and whatever of its settings are known.
        columns: the input's column names.
        fit: tune the estimator on the data first (:func:`~torchsvs.training.tuning.self_tune`).
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
            found = BlockEstimates.empty(steps, covariance)
            tick, cpu = time.perf_counter(), time.process_time()
            for position, group in enumerate(steps.batches(max_cells)):
                batch = group_batch(steps, group, position, dtype)
                found.add(
                    estimate_group(estimator, batch, meas_std, covariance, accuracy, run.settings)
                )
                bar.update(len(group))
            run.estimate_seconds += time.perf_counter() - tick
            run.estimate_cpu_seconds += time.process_time() - cpu
            run.report.add(steps.report)
            run.report.notes.update(found.notes)
            for factors in found.q_factors:
                run.q_factors.update(factors.tolist())
            if run.risk is not None:
                for terms in found.risk:
                    run.risk.add(terms)
                run.add_track_errors(found.risk, steps.ids)
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


def settings_note(settings: Settings) -> str:
    """One line on the model's noise levels and where the measurement noise came from."""
    assert settings.meas_var is not None
    std = ", ".join(f"{v**0.5:.4g}" for v in settings.meas_var)
    source = {"given": "as given", "fit": "learned"}.get(settings.noise or "", "read off the data")
    if settings.noise == "data" and settings.meas_std_se is not None:
        source += " ± " + ", ".join(f"{e:.2g}" for e in settings.meas_std_se)
    return (
        f"model: measurement noise std [{std}] ({source}), q = {settings.q:.4g}, "
        f"typical interval {settings.interval:.4g} s"
    )


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
    off them (:func:`complete_settings`, on up to ``fit_options["tracks"]`` tracks spread over
    the block), then fitted, loaded from ``checkpoint``, saved to ``save``, as asked.

    Returns:
        The estimator (float64), the settings it was built from, and the fit's summary (or
        ``None``).
    """
    say = say or (lambda _: None)
    sample = steps.pad(_sample_tracks(steps, fit_options), torch.float64)
    open_q = settings.q is None
    if settings.estimator != "auto":
        settings = complete_settings(settings, sample)
        say(settings_note(settings))
    summary: Any = None
    options = dict(fit_options or {})
    options.pop("tracks", None)
    if settings.estimator == "auto":
        from torchsvs.training.selection import choose_estimator

        options.pop("known_noise", None)
        summary = choose_estimator(settings, sample, say=say, **options)
        settings = summary.settings
        say(summary.summary())
    elif fit:
        from torchsvs.training.tuning import self_tune

        summary = self_tune(settings, sample, **options)
        settings = summary.settings
        say(summary.summary())
    if open_q and checkpoint is None:
        settings = with_q_curve(settings, sample)
    estimator = make_estimator(settings, make_model(settings))
    if checkpoint is not None:
        load_parameters(estimator, checkpoint)
    if save is not None:
        torch.save({"settings": asdict(settings), "state_dict": estimator.state_dict()}, save)
    return estimator, settings, summary


def with_q_curve(settings: Settings, tracks: RecordedTracks) -> Settings:
    """The settings with the file's SURE curve of ``q`` (``q_curve``, read off ``tracks``), so
    that each track runs with its own ``q``; unchanged where ``settings.track_q`` is off, for
    the IMM (its modes' noises are one design) and where the tracks give nothing to score."""
    from torchsvs.training import noise

    if not settings.track_q or settings.estimator in ("imm", "auto"):
        return settings
    assert settings.meas_var is not None and settings.q is not None
    curves = noise.q_curves(
        tracks.z, tracks.dt, settings.meas_var, settings.q, settings.estimator not in FILTERS
    )
    if float(curves.counts.sum()) == 0:
        return settings
    return replace(settings, q_curve=curves.pooled())


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

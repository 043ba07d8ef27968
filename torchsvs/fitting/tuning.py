"""Self-tuning on the user's own tracks, without truth (``torchsvs track --fit``).

Two stages, each a short L-BFGS run on (at most 64) windows of 128 steps cut from the tracks
(:func:`~torchsvs.training.data.recorded_batches`), with the losses of
:mod:`torchsvs.fitting.losses`:

1. **The sensor's noise, when it is not given**: a Kalman filter on the same nearly-constant
   velocity model learns ``q`` and ``R`` by maximum likelihood (innovation NLL). ``R`` is then
   taken as known.
2. **The estimator's own parameters** (``q``; the SVSF's ψ and γ; the IMM's turn-mode noises
   ``turn_q`` and ``turn_rate_q`` beside its CV mode's ``q``) by Stein's unbiased risk
   estimate of the position MSE with that ``R`` (:func:`~torchsvs.fitting.losses.stein_risk`):
   the loss that targets the error users care about, while the NLL only scores one-step
   predictions.

The IMM's noises and the RSTKF's ``q`` are not descended but searched (:func:`_imm_search`,
:func:`_q_search`: scaled candidates scored by SURE on short windows): their step loops of small
tensors make each gradient cost seconds. Parameters are moved in
log space (ψ, q, R) and logit space (γ). The SURE surface of an SVSS
has more than one valley, so stage 2 first compares a few starting points (:data:`START_Q`,
:data:`START_PSI`) by their risk and descends from the best; ψ is shared by the axes.
Measured on recorded flights (``experiments/results/real_flights.md``): seconds per fit, within
1% of the best grid value on held-out flights.
"""

from __future__ import annotations

import math
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from typing import Any

import torch
from torch import Tensor, nn
from torch.nn.utils import parametrize

from torchsvs.datasets import RecordedTracks
from torchsvs.estimator import threads_for
from torchsvs.filters import SVSF
from torchsvs.fitting.batches import TrackBatch, batch_loss, recorded_batches
from torchsvs.recipes import Settings, make_estimator, make_model, rule_of_thumb_psi

#: Estimators whose parameters ``self_tune`` fits by their own SURE.
TUNABLE = ("kf", "ks", "ekf", "ukf", "rstkf", "svsf", "svss", "svstps", "imm")
#: Particle filters: their SURE is random (the particles), so their q is the Kalman filter's on
#: the same motion model (a filter, as they are); their other settings stay as given.
TWINS = {"pf": "kf", "spvsf": "kf"}


@dataclass
class FitResult:
    """What a fit learned and what it cost."""

    settings: Settings  #: the learned values
    seconds: float = 0.0
    stages: list[str] = field(default_factory=list)  #: one line per stage
    curve: list[float] = field(default_factory=list)  #: the last stage's loss per step
    #: how many values the SURE descent learned on the tracks (ψ tied over the axes counts
    #: once): what a comparison on the same tracks owes for them (:func:`~torchsvs.selection.
    #: checked_layer`)
    parameters: int = 0

    def summary(self) -> str:
        return "fit: " + "; ".join(self.stages) + f" ({self.seconds:.1f} s)"


@contextmanager
def eager_optimizers() -> Iterator[None]:
    """Within this block torch.optim's L-BFGS methods that are marked not to be traced by
    ``torch.compile`` (``torch._disable_dynamo``: ``add_param_group``, ``zero_grad``, ...)
    call their functions directly. Marked, each imports ``torch._dynamo`` at its first call to
    say so (1.1-1.4 s here, a third of ``track --estimator imm --fit`` on ten thousand rows);
    the fit runs eagerly, never under ``torch.compile``, so there is nothing to say. Each
    method's cached wrapper (the marker's own ``__dynamo_disable`` attribute) is the function
    itself until the block ends, then removed: a later call marks it as torch does. Nothing
    changes where ``torch._dynamo`` is already imported or the marker is not torch's."""
    marker = getattr(getattr(torch, "_compile", None), "_disable_dynamo", None)
    set_here: list[Any] = []
    if marker is not None and "torch._dynamo" not in sys.modules:
        code = marker(lambda: None).__code__
        for klass in torch.optim.LBFGS.__mro__:  # (Adam's step imports Dynamo itself)
            for value in vars(klass).values():
                fn = getattr(value, "__wrapped__", None)
                marked = getattr(value, "__code__", None) is code and fn is not None
                if marked and not hasattr(fn, "__dynamo_disable"):
                    setattr(fn, "__dynamo_disable", fn)
                    set_here.append(fn)
    try:
        yield
    finally:
        for fn in set_here:
            delattr(fn, "__dynamo_disable")


def _minimise(
    module: nn.Module,
    batches: list[TrackBatch],
    loss: str,
    steps: int,
    lr: float,
    meas_cov: Tensor | None = None,
    seed: int = 0,
    optimizer: str = "lbfgs",
) -> list[float]:
    """Minimises a loss over the module's learnable parameters; returns the loss per evaluation.

    ``"lbfgs"``: L-BFGS with a strong-Wolfe line search on a deterministic objective (the SURE
    probes are drawn from the same seed at every evaluation), at most ``steps`` evaluations:
    a handful of parameters in log space converge in a few dozen. ``"adam"``: ``steps`` Adam
    steps with a cosine-decayed rate ``lr`` and fresh probes each step.
    """
    params = [p for p in module.parameters() if p.requires_grad]
    curve: list[float] = []
    total_windows = sum(len(b.z) for b in batches)

    def evaluate(probes: torch.Generator) -> Tensor:
        total = torch.zeros((), dtype=torch.float64)
        for batch in batches:
            with threads_for(*batch.x0.shape):  # the backward pass too, not only forward
                value, _ = batch_loss(module, batch, loss, meas_cov=meas_cov, generator=probes)
                weighted = value * (len(batch.z) / total_windows)
                weighted.backward()
            total = total + weighted.detach()
        curve.append(float(total))
        return total

    if optimizer == "lbfgs":
        with eager_optimizers():
            lbfgs = torch.optim.LBFGS(
                params, lr=1.0, max_iter=steps, max_eval=steps, line_search_fn="strong_wolfe"
            )

            def closure() -> Tensor:
                lbfgs.zero_grad()
                return evaluate(torch.Generator().manual_seed(seed))

            lbfgs.step(closure)
        return curve
    if optimizer != "adam":
        raise ValueError(f"optimizer: expected 'lbfgs' or 'adam', got {optimizer!r}")
    adam = torch.optim.Adam(params, lr=lr)
    schedule = torch.optim.lr_scheduler.CosineAnnealingLR(adam, T_max=steps, eta_min=lr / 20)
    probes = torch.Generator().manual_seed(seed)
    for _ in range(steps):
        adam.zero_grad()
        evaluate(probes)
        adam.step()
        schedule.step()
    return curve


def self_tune(
    settings: Settings,
    tracks: RecordedTracks,
    known_noise: bool = True,
    steps: int = 20,
    noise_steps: int = 20,
    lr: float = 0.1,
    window: int = 128,
    burn_in: int = 16,
    max_windows: int = 64,
    seed: int = 0,
    optimizer: str = "lbfgs",
    tie_axes: bool = True,
) -> FitResult:
    """Tunes an estimator of :mod:`torchsvs.recipes` on recorded tracks, without truth.

    Args:
        settings: complete :class:`~torchsvs.recipes.Settings` (noise levels filled in).
        tracks: the tracks to tune on (float64 is used inside).
        known_noise: the settings' measurement noise is the sensor's (SURE uses it as is);
            ``False`` learns it first (stage 1).
        steps, noise_steps: loss evaluations (L-BFGS) or steps (Adam) of stage 2 and stage 1.
        lr: Adam's learning rate (relative steps in log ψ, log q, logit γ, log R).
        optimizer: ``"lbfgs"`` (default) or ``"adam"`` (see :func:`_minimise`).
        tie_axes: one ψ for the positions of every axis and one for their velocities (the
            axes of a track are alike; per-axis widths fit the noise of a few tracks).
        window, burn_in: windows the tracks are cut into (:func:`recorded_batches`).
        max_windows: at most this many windows, spread evenly over all of them.
        seed: of the window sample and the SURE probes.

    Returns:
        A :class:`FitResult` whose ``settings`` hold the learned values.
    """
    if settings.estimator in TWINS:
        twin = TWINS[settings.estimator]
        result = self_tune(
            replace(settings, estimator=twin),
            tracks,
            known_noise,
            steps,
            noise_steps,
            lr,
            window,
            burn_in,
            max_windows,
            seed,
            optimizer,
            tie_axes,
        )
        fitted = result.settings
        result.settings = replace(
            settings, q=fitted.q, meas_var=fitted.meas_var, noise=fitted.noise
        )
        result.stages.append(
            f"{settings.estimator}: q = {_fmt(fitted.q)} from the {twin}'s fit (a particle "
            "filter's own loss is random)"
        )
        return result
    if settings.estimator not in TUNABLE:
        raise ValueError(
            f"estimator: --fit tunes {', '.join(TUNABLE + tuple(TWINS))}; got "
            f"{settings.estimator!r}"
        )
    start = time.perf_counter()
    result = FitResult(settings)
    tracks = tracks.to(torch.float64)

    def batches_for(
        meas_var: list[float],
        window: int | None = window,
        burn_in: int = burn_in,
        most: int = max_windows,
    ) -> list[TrackBatch]:
        all_windows = recorded_batches(
            tracks, torch.tensor(meas_var, dtype=torch.float64), window, burn_in, None
        )[0]
        count = len(all_windows.z)
        if count <= most:
            return [all_windows]
        pick = torch.linspace(0, count - 1, most).round().long().unique()
        return [TrackBatch(*(_rows(field, pick) for field in all_windows))]

    if not known_noise:
        assert settings.meas_var is not None
        kf_settings = replace(settings, estimator="kf", lag=None)  # the filter of a smoother
        model = make_model(kf_settings, learn_q=True, learn_r=True).double()
        kf = make_estimator(kf_settings, model)
        curve = _minimise(
            kf,
            batches_for(settings.meas_var),
            "nll",
            noise_steps,
            lr,
            seed=seed,
            optimizer=optimizer,
        )
        meas_var = model.meas_cov().detach().diagonal().tolist()
        q = float(model.q().detach())
        settings = replace(settings, meas_var=meas_var, q=q, noise="fit")
        std = ", ".join(f"{v**0.5:.4g}" for v in meas_var)
        result.stages.append(
            f"noise by innovation NLL: measurement std [{std}], q = {q:.4g} "
            f"(NLL {curve[0]:.4f} → {curve[-1]:.4f})"
        )

    if settings.psi is None and settings.estimator in ("svsf", "svss", "svstps"):
        assert settings.meas_var is not None
        settings = replace(
            settings,
            psi=rule_of_thumb_psi(len(settings.meas_var), settings.velocity, settings.estimator),
        )
    assert settings.meas_var is not None
    meas_cov = torch.diag(torch.tensor(settings.meas_var, dtype=torch.float64))
    whole = batches_for(settings.meas_var, None, 0, CHECK_TRACKS)  # (the fit checked on them)
    if settings.estimator in SEARCHED:
        batches = batches_for(settings.meas_var, *SEARCH_WINDOWS)
        search = SEARCHED[settings.estimator]
        result.settings = search(settings, (batches, whole), meas_cov, seed, result)
        result.seconds = time.perf_counter() - start
        return result
    batches = batches_for(settings.meas_var)
    settings = _best_start(settings, batches, meas_cov, seed)
    model = make_model(settings, learn_q=True, learn_r=False).double()
    estimator = make_estimator(settings, model).double()
    for svsf in _svsfs(estimator):
        if tie_axes:
            kinds = 2 if svsf.artificial is not None else 1  # (position, velocity) or position
            parametrize.register_parametrization(svsf.boundary_layer, "raw", _TiedAxes(kinds))
    start_settings = settings
    result.parameters = sum(p.numel() for p in estimator.parameters() if p.requires_grad)
    curve = _minimise(
        estimator, batches, "sure", steps, lr, meas_cov=meas_cov, seed=seed, optimizer=optimizer
    )
    # A still target drives q to 0 (log q → −∞): floor it where it no longer matters.
    assert settings.meas_var is not None
    floor = Q_FLOOR * sum(settings.meas_var) / len(settings.meas_var) / settings.interval**3
    learned: dict[str, Any] = {"q": max(float(model.q().detach()), floor)}
    for svsf in _svsfs(estimator):
        learned["psi"] = [float(p) for p in svsf.psi.detach().reshape(-1)]
        learned["gamma"] = float(svsf.gamma.detach())
        if tie_axes:
            parametrize.remove_parametrizations(svsf.boundary_layer, "raw")
    settings = replace(settings, **learned)
    shown = ", ".join(f"{k} = {_fmt(v)}" for k, v in learned.items())
    result.settings = _checked_fit(
        start_settings,
        settings,
        whole,
        meas_cov,
        seed,
        result,
        lambda began, ended: (
            f"{settings.estimator} by SURE: {shown} (risk {curve[0]:.4f} → {curve[-1]:.4f} of "
            f"R; fresh probes {began:.4f} → {ended:.4f})"
        ),
    )
    result.curve = curve
    result.seconds = time.perf_counter() - start
    return result


#: Starting points the fit compares before descending: factors on q, and on ψ for the SVSF family
#: (the SURE surface of an SVSS has a valley of narrow boundary layers, where the SVSF follows its
#: pseudo-measurements and the smoother does the work, and one of wide ones).
START_Q = (0.3, 1.0, 3.0)
#: The least q a fit returns, in units of r / T³ (a still target's q goes to 0).
Q_FLOOR = 1e-12
#: Seed offset of the probes that check a fit's result (apart from the descent's).
VALIDATION_SEED = 7919
START_PSI = (0.03, 0.2, 1.0)


#: The searched fits' windows (:data:`SEARCHED`): this many steps, this many burnt in, at most
#: this many windows. An IMM's or an RSTKF's steps are dozens of small tensor operations each
#: (the RSTKF's 10 variational iterations), so a pass costs its steps, not its points: short
#: windows side by side make a pass of thousands of points a fraction of a second. Measured on
#: the recorded-tracks benchmark with the IMM: 48-step windows chose alike, for 20% more time;
#: 256 windows at most (with the smoother's cost) chose within 0.5% of 512 on six sets, 3% behind
#: on taxiing aircraft (σ 50).
SEARCH_WINDOWS = (32, 8, 256)
#: A fit's choice (searched or descended) is checked against its start on this many whole
#: tracks (spread over the sample), fresh probes: what runs. On 32-step windows the RSTKF's
#: SURE fell to 0.66 of R at ``q`` 0.0018 times the reading's on airliners at σ 25 m (each
#: window starts afresh, and its variational step follows a turn for a few steps), where on the
#: whole tracks that ``q`` came out at 1.46 of the measurements' error (the start 0.85).
CHECK_TRACKS = 256
#: Factors on the three process noises of the IMM together (``q``, ``turn_q``, ``turn_rate_q``
#: as :func:`~torchsvs.fitting.defaults.turn_settings` derives them), then on the turn-rate
#: noise alone, then on the turn mode's acceleration noise alone: the candidates
#: :func:`_imm_search` scores by SURE.
IMM_FACTORS = tuple(10.0 ** (k / 2) for k in range(-2, 3))
IMM_RATE_FACTORS = tuple(10.0 ** (k / 2) for k in range(-1, 2))


def _imm_search(
    settings: Settings,
    samples: tuple[list[TrackBatch], list[TrackBatch]],
    meas_cov: Tensor,
    seed: int,
    result: FitResult,
) -> Settings:
    """The IMM's process noises by a search over :data:`IMM_FACTORS` on all three together,
    then :data:`IMM_RATE_FACTORS` on the turn-rate noise, then on ``turn_q``, each candidate
    scored by its SURE (forward passes only, the same probes); the choice is checked against the
    start with fresh probes (kept only if lower). No gradients: a descent through the IMM's steps
    took 30-110 s on 5,000 rows for 0-10% of error (``experiments/results/recorded_tracks.md``);
    this takes seconds and lands within 2% of it (better on gliders: 0.98 of raw, was 1.07).
    ``samples``: the windows scored, the whole tracks the choice is checked on."""
    batches, whole = samples
    scored = 0

    def risk_of(candidate: Settings) -> float:
        nonlocal scored
        scored += 1
        return _settings_risk(candidate, batches, meas_cov, seed)

    def noise(base: Settings, name: str, factor: float) -> float:
        value = getattr(base, name)
        assert value is not None
        return float(value) * factor

    def together(base: Settings, f: float) -> Settings:
        return replace(
            base,
            q=noise(base, "q", f),
            turn_q=noise(base, "turn_q", f),
            turn_rate_q=noise(base, "turn_rate_q", f),
        )

    def rate(base: Settings, f: float) -> Settings:
        return replace(base, turn_rate_q=noise(base, "turn_rate_q", f))

    def turn(base: Settings, f: float) -> Settings:
        return replace(base, turn_q=noise(base, "turn_q", f))

    best = settings
    start_risk = risk = risk_of(settings)
    chosen = []
    for factors, scale in (
        (IMM_FACTORS, together),
        (IMM_RATE_FACTORS, rate),
        (IMM_RATE_FACTORS, turn),
    ):
        scores = {f: risk if f == 1.0 else risk_of(scale(best, f)) for f in factors}
        factor = min(scores, key=scores.__getitem__)
        best, risk = scale(best, factor), scores[factor]
        chosen.append(factor)
    result.parameters = len(chosen)  # (three values chosen on the tracks, as a descent learns)
    return _checked_fit(
        settings,
        best,
        whole,
        meas_cov,
        seed,
        result,
        lambda began, ended: (
            f"imm by SURE: noises ×{chosen[0]:.3g}, then turn-rate noise ×{chosen[1]:.3g}, turn "
            f"mode's acceleration ×{chosen[2]:.3g}: q = {_fmt(noise(best, 'q', 1.0))}, turn_q = "
            f"{_fmt(noise(best, 'turn_q', 1.0))}, turn_rate_q = "
            f"{_fmt(noise(best, 'turn_rate_q', 1.0))} (risk {start_risk:.4f} → {risk:.4f} of R; "
            f"fresh probes {began:.4f} → {ended:.4f}; {scored} candidates)"
        ),
    )


def _checked_fit(
    start: Settings,
    best: Settings,
    whole: list[TrackBatch],
    meas_cov: Tensor,
    seed: int,
    result: FitResult,
    stage: Callable[[float, float], str],
) -> Settings:
    """A fit's choice ``best`` (searched or descended) checked against ``start`` by their SURE
    on the ``whole`` tracks (:data:`CHECK_TRACKS`) with fresh probes, kept only where its risk
    is not higher; the fit's line (``stage`` of the two fresh risks) added to ``result``. The
    fit saw one set of probes on windows: an estimator very sensitive to its input can flatter
    them, and a window that starts afresh can flatter a choice the whole tracks do not bear."""
    fresh = seed + VALIDATION_SEED
    began, ended = (_settings_risk(s, whole, meas_cov, fresh) for s in (start, best))
    result.stages.append(stage(began, ended))
    if not ended <= began:
        result.stages.append(
            "kept the starting point: with fresh probes the fit's risk was not lower"
        )
        return start
    return best


#: :func:`_q_search`'s factors on ``q``: decades from 10⁻⁵ to 10 times the start, then half and
#: quarter decades around the best. The RSTKF's variational step inflates a small nominal ``Q``
#: itself, so its SURE falls over decades below the noise reading's ``q`` and then stays flat
#: (aircraft at σ 40 m: 0.91 of R at the reading, 0.80 from 0.03 down).
Q_DECADES = tuple(10.0**k for k in range(-5, 2))
Q_REFINE = (10.0**-0.5, 10.0**0.5), (10.0**-0.25, 10.0**0.25)


def _q_search(
    settings: Settings,
    samples: tuple[list[TrackBatch], list[TrackBatch]],
    meas_cov: Tensor,
    seed: int,
    result: FitResult,
) -> Settings:
    """``q`` by a search over :data:`Q_DECADES`, then :data:`Q_REFINE` around the best, each
    candidate scored by its SURE (forward passes only, the same probes); checked against the
    start with fresh probes (kept only if lower). For an estimator whose step is a loop of small
    tensors (the RSTKF): L-BFGS through its steps took 71 s on 5,000 rows. ``samples``: the
    windows scored, the whole tracks the choice is checked on."""
    batches, whole = samples
    assert settings.q is not None
    start = settings.q
    scores: dict[float, float] = {}

    def scaled(factor: float) -> Settings:
        return replace(settings, q=start * factor)

    for factor in Q_DECADES:
        scores[factor] = _settings_risk(scaled(factor), batches, meas_cov, seed)
    for steps in Q_REFINE:
        best = min(scores, key=scores.__getitem__)
        for step in steps:
            scores[best * step] = _settings_risk(scaled(best * step), batches, meas_cov, seed)
    best = min(scores, key=scores.__getitem__)
    result.parameters = 1
    chosen = scaled(best)
    return _checked_fit(
        scaled(1.0),
        chosen,
        whole,
        meas_cov,
        seed,
        result,
        lambda began, ended: (
            f"{settings.estimator} by SURE: q = {_fmt(chosen.q)} (×{best:.3g}; risk "
            f"{scores[1.0]:.4f} → {scores[best]:.4f} of R; fresh probes {began:.4f} → "
            f"{ended:.4f}; {len(scores)} candidates)"
        ),
    )


#: Estimators whose fit searches rather than descends: their searches.
SEARCHED = {"imm": _imm_search, "rstkf": _q_search}


def _best_start(
    settings: Settings, batches: list[TrackBatch], meas_cov: Tensor, seed: int
) -> Settings:
    """The candidate start with the lowest SURE (forward passes only, same probes)."""
    assert settings.q is not None
    widths = START_PSI if settings.psi is not None else (1.0,)
    best, best_risk = settings, math.inf
    for q_factor in START_Q:
        for psi_factor in widths:
            candidate = replace(
                settings,
                q=settings.q * q_factor,
                psi=None if settings.psi is None else [p * psi_factor for p in settings.psi],
            )
            risk = _settings_risk(candidate, batches, meas_cov, seed)
            if risk < best_risk:
                best, best_risk = candidate, risk
    return best


def _settings_risk(
    candidate: Settings, batches: list[TrackBatch], meas_cov: Tensor, seed: int
) -> float:
    """:func:`_risk` of the float64 estimator the settings make."""
    return _risk(make_estimator(candidate, make_model(candidate)).double(), batches, meas_cov, seed)


def _risk(estimator: nn.Module, batches: list[TrackBatch], meas_cov: Tensor, seed: int) -> float:
    """SURE of an estimator on the batches (forward passes, probes from ``seed``), in units of R
    per observed component."""
    total = sum(len(b.z) for b in batches)
    with torch.no_grad():
        return sum(
            float(
                batch_loss(
                    estimator,
                    b,
                    "sure",
                    meas_cov=meas_cov,
                    generator=torch.Generator().manual_seed(seed),
                    keep="mean",
                )[0]
            )
            * len(b.z)
            / total
            for b in batches
        )


class _TiedAxes(nn.Module):
    """``log ψ`` per component from one value per kind (position[, velocity]), shared by the
    axes: components in state order ``p1, v1, p2, v2, ...`` (or ``p1, p2, ...``)."""

    def __init__(self, kinds: int) -> None:
        super().__init__()
        self.kinds = kinds

    def forward(self, shared: Tensor) -> Tensor:
        return shared.repeat(self._axes)

    def right_inverse(self, raw: Tensor) -> Tensor:
        values = raw.reshape(-1)
        self._axes = max(1, values.numel() // self.kinds)
        return values.reshape(self._axes, self.kinds).mean(dim=0) if values.numel() > 1 else values


def _svsfs(module: nn.Module) -> list[SVSF]:
    return [m for m in module.modules() if isinstance(m, SVSF)]


def _rows(value: Any, pick: Tensor) -> Any:
    """Rows ``pick`` of a batch field (tensors over windows), other fields unchanged."""
    if isinstance(value, Tensor) and value.ndim >= 2:
        return value[pick]
    return value


def _fmt(value: Any) -> str:
    if isinstance(value, list):
        return "[" + ", ".join(_fmt(v) for v in value) + "]"
    return f"{value:.4g}" if isinstance(value, float) and math.isfinite(value) else str(value)

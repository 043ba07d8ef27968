"""The IMM of a nearly-constant-velocity mode and a coordinated-turn mode, in the constant
velocity state: what ``torchsvs track --estimator imm`` runs on recorded tracks."""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import torch
from torch import Tensor, nn

from torchsvs.estimator import Estimator, Inputs, drop_batch, prepare_inputs, threads_for
from torchsvs.filters.gaussian import GaussianFilter
from torchsvs.filters.imm import IMM, IMM_PROBE_STEP, IMMResult
from torchsvs.filters.kalman import KalmanFilter
from torchsvs.filters.nonlinear import ExtendedKalmanFilter, UnscentedKalmanFilter
from torchsvs.kernels.compiled import outside_dynamo
from torchsvs.kernels.fused_imm import TurnIMMPass, turn_imm_run
from torchsvs.models.base import StateSpaceModel
from torchsvs.models.motion import ConstantVelocity, CoordinatedTurn
from torchsvs.models.turn import CoordinatedTurn3D
from torchsvs.types import FilterResult

#: The mode switch probability per step of the default transition matrix.
SWITCH_PROB = 0.05


class TurnIMM(Estimator[IMMResult]):
    r"""IMM(CV, CT): a Kalman filter on a nearly-constant-velocity model and an extended (or
    unscented) Kalman filter on a coordinated turn with unknown turn rate, mixed by an
    :class:`~torchsvs.filters.IMM`, estimating the constant-velocity state.

    The estimator is called like every other (``est(z, x0, P0, dt=...)``) with the CV model's
    state: ``x0 [B, n]``, ``P0`` in the layout ``[x, vx, y, vy(, z, vz)]`` (``n = 2·ndim``), and
    its result's ``mean``/``cov`` are the combined estimate in that layout. Inside, the IMM's
    common state appends the turn rate ω (rad/s, counter-clockwise positive): the prior gives
    it mean 0 and standard deviation ``turn_rate_std``, the CV mode lacks it (embedding
    ``[[0, ..., n-1], [0, ..., n]]``, mixed without bias: the CV mode leaves the CT mode's ω
    where it was), and the combined estimate drops it (its value in the combined state would be
    :math:`\mu_{CT}\,\hat\omega`); the result's ``modes`` hold each mode's own estimates (the
    CT mode's ω at index ``n``) and ``mode_probs [B, T, 2]`` the probabilities of (CV, CT).

    Modes:

    * CV: :class:`~torchsvs.filters.KalmanFilter` on ``model``
      (:class:`~torchsvs.models.ConstantVelocity`, white acceleration of spectral density
      ``q``).
    * CT: for ``ndim = 2`` a :class:`~torchsvs.models.CoordinatedTurn` (white acceleration of
      variance ``turn_q`` per axis, turn-rate noise ``turn_rate_q``); for ``ndim = 3`` a
      :class:`~torchsvs.models.CoordinatedTurn3D`: the turn in the horizontal ``x, y`` plane and
      a vertical axis that is the CV model's own (its ``q``, shared), so height is estimated the
      same way in both modes and only the horizontal motion decides between them.

    Both modes measure the positions with the CV model's ``R`` (one parameter, shared).

    The turn rate is estimated by the EKF from positions alone: a turn-rate noise much larger
    than the data support lets it wander, on noisy tracks with long gaps, to values whose turn
    over one interval is several radians, where the linearisation means nothing and the turn
    mode's velocity diverges (measured on recorded flights, ``experiments/results/
    real_flights.md``); :func:`torchsvs.fitting.defaults.turn_settings` derives a safe scale
    from the data.

    Args:
        model: the CV mode's :class:`~torchsvs.models.ConstantVelocity`, 2 or 3 axes.
        turn_q: the CT mode's white acceleration variance per horizontal axis (m²/s⁴);
            default ``q / T``: the same velocity noise per step as the CV mode.
        turn_rate_q: the CT mode's turn-rate noise (rad²/s⁴), > 0.
        turn_rate_std: prior standard deviation of ω (rad/s), > 0.
        transition: the ``[2, 2]`` mode transition matrix, rows (from CV, from CT); default
            :data:`SWITCH_PROB` off the diagonal.
        turn_filter: ``"ekf"`` (default; the analytic Jacobian) or ``"ukf"``.
        learn_turn_noise: learn ``turn_q`` and ``turn_rate_q`` (through their logs); default
            ``None``: when the CV model's ``q`` is learnable (so a fit of ``model.q`` tunes all
            three process noises).

    References:
        Blom, Bar-Shalom, IEEE Trans. Autom. Control 33(8), 1988. doi:10.1109/9.1299 ·
        Bar-Shalom, Li, Kirubarajan, "Estimation with Applications to Tracking and Navigation",
        Wiley 2001, Secs. 11.6.6, 11.7 (the CV-CT IMM of its Sec. 11.7.4 example). ·
        Li, Jilkov, "Survey of maneuvering target tracking. Part V: Multiple-model methods",
        IEEE Trans. Aerosp. Electron. Syst. 41(4), 2005. doi:10.1109/TAES.2005.1561886
    """

    paired_probes = True  # the plain and probed runs in one pass (one call of a step loop)
    model: ConstantVelocity
    probe_step = IMM_PROBE_STEP

    def __init__(
        self,
        model: ConstantVelocity,
        turn_rate_q: float,
        turn_rate_std: float,
        turn_q: float | None = None,
        transition: Any = None,
        turn_filter: str = "ekf",
        learn_turn_noise: bool | None = None,
    ) -> None:
        super().__init__()
        if not isinstance(model, ConstantVelocity):
            raise TypeError(f"model: expected a ConstantVelocity, got {type(model).__name__}")
        if model.ndim not in (2, 3):
            raise ValueError(f"model: expected 2 or 3 axes, got a ConstantVelocity of {model.ndim}")
        for name, value in (("turn_rate_q", turn_rate_q), ("turn_rate_std", turn_rate_std)):
            if not _positive(value):
                raise ValueError(f"{name}: expected a number > 0, got {value!r}")
        if turn_q is None:
            turn_q = float(model.q().detach()) / model.dt
        elif not _positive(turn_q):
            raise ValueError(f"turn_q: expected a number > 0, got {turn_q!r}")
        if turn_filter not in ("ekf", "ukf"):
            raise ValueError(f"turn_filter: expected 'ekf' or 'ukf', got {turn_filter!r}")
        if learn_turn_noise is None:
            learn_turn_noise = isinstance(model.q.raw, nn.Parameter)
        turn: StateSpaceModel
        if model.ndim == 2:
            turn = CoordinatedTurn(
                dt=model.dt, q=turn_q, q_turn=turn_rate_q, learn_q=learn_turn_noise
            )
        else:
            turn = CoordinatedTurn3D(
                dt=model.dt, q=turn_q, q_turn=turn_rate_q, learn_q=learn_turn_noise
            )
            turn.vertical.q = model.q  # the height axis is the CV model's in both modes
        turn.R = model.R  # one measurement noise for both modes
        turn = turn.to(model.H.dtype)
        cv_filter: GaussianFilter = KalmanFilter(model)
        turn_filter_: GaussianFilter = (
            ExtendedKalmanFilter(turn) if turn_filter == "ekf" else UnscentedKalmanFilter(turn)
        )
        n = model.state_dim
        if transition is None:
            transition = [[1 - SWITCH_PROB, SWITCH_PROB], [SWITCH_PROB, 1 - SWITCH_PROB]]
        self.imm = IMM(
            [cv_filter, turn_filter_],
            transition,
            embedding=[list(range(n)), list(range(n + 1))],
        )
        self.model = model
        self.turn_model = turn
        self.turn_rate_std = float(turn_rate_std)

    @property
    def turn_q(self) -> Tensor:
        """The CT mode's white acceleration variance per horizontal axis (m²/s⁴)."""
        return _plane(self.turn_model).q()

    @property
    def turn_rate_q(self) -> Tensor:
        """The CT mode's turn-rate noise (rad²/s⁴)."""
        return _plane(self.turn_model).q_turn()

    @outside_dynamo
    def forward(
        self,
        z: Tensor,
        x0: Tensor,
        P0: Tensor,
        *,
        mode_probs: Any = None,
        u: Tensor | None = None,
        dt: float | Tensor | None = None,
        psi: Tensor | None = None,
        generator: torch.Generator | None = None,
        keep: str = "all",
    ) -> IMMResult:
        """Runs the IMM over every track: ``z [B, T, m]`` (or ``[T, m]``), the CV-state prior
        ``x0 [B, n]``, ``P0`` one step before ``z[:, 0]``, ``mode_probs`` (``[2]`` or
        ``[B, 2]``, probabilities of CV and CT; default uniform), ``dt`` and ``keep`` as for
        every estimator. Returns an :class:`~torchsvs.filters.IMMResult` whose ``mean`` and
        ``cov`` are in the CV state."""
        self.check_psi(psi)
        inputs = prepare_inputs(self.model, z, x0, P0, u=u, dt=dt, generator=generator, keep=keep)
        with threads_for(inputs.batch, self.model.state_dim + 1):
            result = self._pass(inputs, mode_probs)
        result = IMM.trim(result, keep)
        return drop_batch(result) if inputs.single else result

    def run(self, inputs: Inputs) -> IMMResult:
        return self._pass(inputs, None)

    def _pass(self, inputs: Inputs, mode_probs: Any) -> IMMResult:
        common = self.common_inputs(inputs)
        compiled = self.compiled_pass(common, mode_probs, 0)
        if compiled is None:
            return self.cv_part(self.imm.filter_pass(common, mode_probs))
        return self.cv_part(self.filtered_result(compiled))

    def compiled_pass(self, common: Inputs, mode_probs: Any, lag: int | None) -> TurnIMMPass | None:
        """The pass over checked inputs in the common state, compiled
        (:func:`~torchsvs.kernels.fused_imm.turn_imm_run`: the filter for ``lag=0``, else Kim's
        smoother of that lag, ``None`` the fixed interval), or ``None`` where only the tensor
        path can run it: the UKF turn mode, gradients asked of the noises or the transition,
        and the inputs :func:`~torchsvs.kernels.fused_imm.usable` refuses."""
        if type(self.imm.mode_filters[1]) is not ExtendedKalmanFilter:  # (the UKF is one)
            return None
        if torch.is_grad_enabled() and any(p.requires_grad for p in self.parameters()):
            return None
        with torch.no_grad():
            plane = _plane(self.turn_model)
            f64 = torch.float64
            constants = torch.cat(
                [
                    torch.stack([self.model.q(), plane.q(), plane.q_turn()]).to(f64),
                    self.imm.log_transition(f64).flatten(),
                    self.model.R().to(f64).flatten(),
                ]
            )
            log_p0 = self.imm.initial_log_probs(mode_probs, common.batch, f64)
            return turn_imm_run(constants, self.model.dt, common, log_p0, lag)

    def filtered_result(self, compiled: TurnIMMPass) -> IMMResult:
        """The :class:`~torchsvs.filters.IMMResult` (in the common state) of a compiled pass:
        each mode's filtered moments and total log-likelihood, no predicted mode probabilities
        or per-step mode likelihoods (as ``keep`` other than ``"all"`` trims them)."""
        nothing: Any = None
        modes = tuple(
            FilterResult(
                mean, cov, *(nothing,) * 8, log_likelihood=compiled.mode_log_likelihood[:, j]
            )
            for j, (mean, cov) in enumerate(compiled.modes)
        )
        return IMMResult(
            compiled.mean,
            compiled.cov,
            compiled.mode_probs,
            None,
            None,
            modes,
            compiled.log_likelihood,
        )

    def common_inputs(self, inputs: Inputs) -> Inputs:
        """The checked inputs with the prior in the IMM's common state: the turn rate appended
        with mean 0 and standard deviation ``turn_rate_std``."""
        n = self.model.state_dim
        x0 = torch.cat([inputs.x0, inputs.x0.new_zeros(inputs.x0.shape[0], 1)], dim=-1)
        P0 = inputs.P0.new_zeros(*inputs.P0.shape[:-2], n + 1, n + 1)
        P0[..., :n, :n] = inputs.P0
        P0[..., n, n] = self.turn_rate_std**2
        return replace(inputs, x0=x0, P0=P0)

    def cv_part(self, result: Any) -> Any:
        """A result (the IMM's or its smoother's, a NamedTuple) with its combined ``mean`` and
        ``cov`` in the CV state (the turn rate dropped), and a smoother's ``filtered`` pass too."""
        n = self.model.state_dim
        cov = None if result.cov is None else result.cov[..., :n, :n]
        result = result._replace(mean=result.mean[..., :n], cov=cov)
        filtered = getattr(result, "filtered", None)
        return result if filtered is None else result._replace(filtered=self.cv_part(filtered))


def _plane(model: StateSpaceModel) -> CoordinatedTurn:
    return model.plane if isinstance(model, CoordinatedTurn3D) else model  # type: ignore[return-value]


def _positive(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and value > 0

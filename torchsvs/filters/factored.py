r"""Numerically robust covariance forms: the Gaussian filters' covariance carried as a factor.

A :class:`~torchsvs.filters.KalmanFilter` (and so an
:class:`~torchsvs.filters.ExtendedKalmanFilter`) or an :class:`~torchsvs.filters.SVSF` built
with ``covariance_form=`` other than ``"joseph"`` carries its covariance between steps in one of
these forms; the estimates, gains and the full covariances of its result (reconstructed from the
factor, so smoothers consume them unchanged) are the Joseph filter's in exact arithmetic. The
forms differ in what rounding does to them:

==================  ==========================================================================
``"joseph"``        ``P`` itself, ``(I − KH)P(I − KH)ᵀ + KRKᵀ``, symmetrised
                    (:func:`torchsvs.linalg.joseph_update`; not in this module): the default.
``"conventional"``  ``P`` itself, ``P⁺ = (I − KH)P⁻`` (Eq. (9) of Bermúdez Ordoñez et al.
                    2020), never symmetrised: the textbook form that rounding drives
                    indefinite (:class:`Full`).
``"sqrt"``          a lower-triangular ``S``, ``P = S Sᵀ``, updated by QR of pre-arrays
                    (:class:`Cholesky`).
``"ud"``            ``P = U D Uᵀ``, ``U`` unit upper triangular, ``D`` diagonal: Thornton's
                    modified weighted Gram–Schmidt and Bierman's scalar updates (:class:`UD`).
``"svd"``           ``P = U D² Uᵀ``, ``U`` orthogonal: the K-SVD filter of Bermúdez Ordoñez et
                    al. 2020, Sec. 4, updated by SVDs of pre-arrays (:class:`SVD`).
==================  ==========================================================================

Every factor type has the same methods, on batched tensors (``[B, n, n]``; a batch axis of 1
broadcasts against the batch of ``H``, ``R`` and ``K``): ``of(P)`` factors a full covariance,
``full()`` reconstructs it, ``predict(F, Q)`` is the time update ``F P Fᵀ + Q``,
``kalman_update(H, R, S)`` is the Kalman measurement update (the gain and the posterior factor)
and ``gain_update(K, H, R)`` the update for a gain that is not the Kalman gain (the SVSF's):
``(I − KH)P(I − KH)ᵀ + KRKᵀ``, Eq. (28) of Chen et al. 2020. The noise covariances enter
through their Cholesky factors (:func:`torchsvs.linalg.cholesky`: ``Q = G Gᵀ``, ``R = C Cᵀ``).

Pre-arrays and what they give (lower-triangular ``L`` from the QR of ``M``: ``M = Q_M R_M``,
``L = R_Mᵀ`` with a nonnegative diagonal, so ``L Lᵀ = Mᵀ M``):

* square root, time update: ``M = [S⁺ᵀFᵀ; Gᵀ]`` (``2n × n``), ``S⁻ = L``.
* square root, Kalman update (Morf and Kailath 1975): the lower-triangularisation of
  ``[[C, HS⁻], [0, S⁻]]`` (QR of its transpose) is ``[[X, 0], [Y, S⁺]]`` with ``X Xᵀ = HPHᵀ +
  R``, ``Y Xᵀ = PHᵀ``: the gain is ``K = Y X⁻¹`` and ``S⁺ S⁺ᵀ = P − YYᵀ = P − PHᵀ(HPHᵀ + R)⁻¹HP``.
* square root, any gain: ``M = [S⁻ᵀ(I − KH)ᵀ; Cᵀ Kᵀ]`` (``(n+m) × n``):
  ``MᵀM = (I − KH)P(I − KH)ᵀ + KRKᵀ``, so ``S⁺ = L``.
* UD, time update (Thornton 1976): ``W = [F U, G]`` with weights ``diag(D, I)``,
  ``P⁻ = W diag(D, I) Wᵀ`` refactored by modified weighted Gram–Schmidt (:func:`_mwgs`).
* UD, Kalman update (Bierman 1977): the components of ``z`` one scalar at a time
  (:func:`_bierman`); a non-diagonal ``R`` is first decorrelated by its Cholesky factor
  (``z' = C⁻¹z``, ``H' = C⁻¹H``, ``R' = I``: the same posterior). The vector gain is the linear
  map the sequence applies to ``e``, accumulated as it runs.
* UD, any gain: ``W = [(I − KH)U, K C]`` with weights ``diag(D, I)``, refactored by the same
  modified weighted Gram–Schmidt.
* SVD, time update, Eqs. (18)-(23): the SVD of ``[D⁺U⁺ᵀFᵀ; Gᵀ]`` (Eq. (20)-(21)) is
  ``W [D'; 0] Vᵀ``, so ``P⁻ = V D'² Vᵀ`` (Eq. (23)): ``U⁻ = V``, ``D⁻ = D'``.
* SVD, Kalman update, Eqs. (24)-(43): the information form ``P⁺⁻¹ = P⁻⁻¹ + HᵀR⁻¹H`` (Eq. (26)) with
  ``R⁻¹ = L Lᵀ`` (Eq. (31); here ``L = C⁻ᵀ``, so ``LᵀH = C⁻¹H``, a triangular solve): the SVD of
  the pre-array ``[LᵀHU⁻; D⁻⁻¹]`` (Eqs. (32)-(33)) gives ``V*, D*`` with ``D⁻⁻² + U⁻ᵀHᵀLLᵀHU⁻ =
  V*D*²V*ᵀ`` (Eq. (34)), so ``U⁺ = U⁻V*``, ``D⁺ = D*⁻¹`` (Eqs. (37)-(38)) and
  ``K = U⁺D⁺²U⁺ᵀHᵀLLᵀ = P⁺HᵀR⁻¹`` (Eqs. (42)-(43)). It needs ``P⁻`` nonsingular (``D⁻⁻¹``).
* SVD, any gain: the SVD of ``[D⁻U⁻ᵀ(I − KH)ᵀ; CᵀKᵀ]``: ``P⁺ = V D'² Vᵀ`` as in the time update.

The K-SVD update's rounding limit (measured on the paper's Example 1, ``H = [[1, 1, 1], [1, 1,
1 + δ]]``, ``R = δ²I``, ``P⁻ = I``): the second measurement lives in the ``δ`` of ``H₁₂``. In
float32 at δ = 1e-7, ``1 + δ`` rounds to ``1 + eps``, one ulp, and half an ulp of ``H₁₂`` moves
the exact ``P⁺`` by 0.14. Forming ``LᵀH = H/δ`` rounds the rows' difference from 1.19 to 1 (an
exact SVD of that pre-array: 1.1 correct digits); the SVD's error, about eps·√6/δ ≈ 2.9, swamps
the middle singular value (1.21) that holds the measurement: 0.5 digits. An update whose first
steps round ``H₁₂`` (an orthogonal SVD or QR pre-array) is then at the mercy of its rounding: over
200 random orthogonal ``U`` of the same ``P⁻ = I`` the median is 0.55 digits, 0.46 with the rows
taken one at a time (rank-one SVDs), 0.76 for ``"sqrt"``; ``"ud"`` keeps 7 where its arithmetic
happens to be exact (Bierman's recursion on ``U = I``, ``h = [1, 1, 1]``), 0.8 with the ``δ`` in
``H``'s first column.

Equation numbers (the text's are partly lost; counted from the displayed equations and the
references to them in the text): Eq. (6) time update, (8) gain, (9) conventional update,
(18)-(23) K-SVD time update, (24)-(28) information form, (31)-(38) K-SVD measurement update,
(39)-(43) its gain, (44) the state update.

Missing components (NaN in ``z``) are handled as the Joseph path handles them: the Kalman update
receives ``H`` with zero rows and ``R`` with an identity block there
(:func:`torchsvs.linalg.mask_measurement`), which every pre-array above turns into a zero column
of the gain; the SVSF's gain already has zero columns there.

What a Kalman filter records beside (``S = HP⁻Hᵀ + R`` and the log-likelihood of the
innovations) is formed from the reconstructed ``P⁻`` as in the Joseph form, whatever the form:
the likelihoods of the forms compare, and a form's robustness does not extend to them.

Gradients: QR, Cholesky, triangular solves and the scalar recursions are differentiable as they
stand. The SVD's singular vectors are not differentiable where singular values coincide (a
constant-velocity model with identical axes has every singular value twice), and
``torch.linalg.svd``'s backward is then infinite or NaN; :func:`right_svd` has its own backward
that drops the terms of coinciding pairs (relative gap under ``1e3·eps``). That is exact for
perturbations that keep the multiplicity (the measurements; a ``q`` shared by identical axes:
the dropped terms multiply zero) and misses a term otherwise: with identical axes, the
gradient with respect to a parameter of one axis only (an entry of ``R``'s factor) is not
the Joseph filter's (``tests/test_covariance_forms.py`` checks the exact cases; the other
forms have no such limit).

References:
    Bermúdez Ordoñez, Arnaldo Valdés, Gómez Comendador, "Engineering Applications of Adaptive
    Kalman Filtering Based on Singular Value Decomposition (SVD)", Appl. Sci. 10(15):5168, 2020.
    doi:10.3390/app10155168 ·
    Morf, Kailath, "Square-root algorithms for least-squares estimation", IEEE Trans. Automatic
    Control 20(4), 1975 ·
    Thornton, Bierman, "Gram-Schmidt algorithms for covariance propagation", Int. J. Control
    25(2), 1977 ·
    Bierman, "Factorization Methods for Discrete Sequential Estimation", Academic Press, 1977 ·
    Grewal, Andrews, "Kalman Filtering: Theory and Practice Using MATLAB", 4th ed., Wiley 2015,
    Ch. 7.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import torch
from torch import Tensor

from torchsvs.linalg import cholesky, matvec, right_psd_solve, symmetrize

#: The values of ``covariance_form=``; ``"joseph"`` is the default and not a factor of this module.
COVARIANCE_FORMS = ("joseph", "conventional", "sqrt", "ud", "svd")


def check_form(value: Any) -> str:
    """``value`` if it names a covariance form, else a ``ValueError`` naming the argument."""
    if not isinstance(value, str) or value not in COVARIANCE_FORMS:
        allowed = ", ".join(map(repr, COVARIANCE_FORMS))
        raise ValueError(f"covariance_form: expected one of {allowed}, got {value!r}")
    return value


def _eye_like(A: Tensor) -> Tensor:
    return torch.eye(A.shape[-1], dtype=A.dtype, device=A.device)


def _batched(*tensors: Tensor) -> list[Tensor]:
    """The tensors with their leading (batch) axes broadcast, ready to be concatenated."""
    lead = torch.broadcast_shapes(*(x.shape[:-2] for x in tensors))
    return [x.expand(*lead, *x.shape[-2:]) for x in tensors]


def _rows(*blocks: Tensor) -> Tensor:
    """Blocks stacked on top of each other (their batch axes broadcast)."""
    return torch.cat(_batched(*blocks), dim=-2)


def _lower_factor(M: Tensor) -> Tensor:
    """Lower-triangular ``L`` with a nonnegative diagonal and ``L Lᵀ = Mᵀ M`` from the QR of the
    (tall or square) array ``M [..., r, c]``, ``r ≥ c``: ``M = Q R``, ``L = Rᵀ`` with the rows of
    ``R`` turned where its diagonal is negative (Householder QR leaves the signs free)."""
    R = torch.linalg.qr(M, mode="reduced")[1]
    sign = torch.where(R.diagonal(dim1=-2, dim2=-1) < 0, -1.0, 1.0).to(R.dtype)
    return (R * sign.unsqueeze(-1)).mT


class _RightSVD(torch.autograd.Function):
    """``M = W diag(s) Vᵀ`` → ``(V, s)``, with the backward of :func:`right_svd`."""

    @staticmethod
    def forward(M: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        W, s, Vh = torch.linalg.svd(M, full_matrices=False)
        return Vh.mT, s, W

    @staticmethod
    def setup_context(ctx: Any, inputs: Any, output: Any) -> None:
        V, s, W = output
        ctx.save_for_backward(W, s, V)
        ctx.mark_non_differentiable(W)

    @staticmethod
    def backward(ctx: Any, gV: Tensor | None, gs: Tensor | None, _: Any) -> Tensor:
        W, s, V = ctx.saved_tensors
        # Only V and s leave: with X = Wᵀ dM V, ds = diag(X) and dV = V Ω, Ω_ij =
        # (s_i X_ij + s_j X_ji) / (s_j² − s_i²), so gM = W [diag(gs) + diag(s)(E ∘ (VᵀgV −
        # gVᵀV))] Vᵀ with E_ij = 1/(s_j² − s_i²), 0 on the diagonal and for coinciding pairs.
        inner = torch.zeros_like(V) if gs is None else torch.diag_embed(gs)
        if gV is not None:
            square = s.square()
            gap = square.unsqueeze(-2) - square.unsqueeze(-1)  # [i, j]: s_j² − s_i²
            tol = 1e3 * torch.finfo(s.dtype).eps * square.amax(-1, keepdim=True).unsqueeze(-1)
            apart = gap.abs() > tol
            E = torch.where(apart, 1.0 / torch.where(apart, gap, 1.0), 0.0)
            Y = V.mT @ gV
            inner = inner + s.unsqueeze(-1) * (E * (Y - Y.mT))
        return W @ inner @ V.mT


def right_svd(M: Tensor) -> tuple[Tensor, Tensor]:
    """``(V, s)`` of the SVD ``M = W diag(s) Vᵀ`` of a pre-array ``M [..., r, c]`` (``r ≥ c``),
    so ``Mᵀ M = V diag(s²) Vᵀ``; the left factor ``W`` is formed (LAPACK forms it anyway) but not
    returned. Its backward is ``torch.linalg.svd``'s for these outputs with the terms of
    coinciding singular values dropped (see the module's notes on gradients)."""
    V, s, _ = _RightSVD.apply(M)
    return V, s


def _mwgs(W: Tensor, weights: Tensor) -> tuple[Tensor, Tensor]:
    """Modified weighted Gram–Schmidt (Thornton 1976; ``thornton.m`` of Grewal and
    Andrews, Ch. 7): ``U`` unit upper
    triangular and ``d`` with ``U diag(d) Uᵀ = W diag(weights) Wᵀ`` for ``W [..., n, N]``,
    ``weights [..., N] ≥ 0``, never forming the product. The rows are orthogonalised under the
    weights from the last up: row ``k`` (reduced by the rows below) gives ``d_k`` and the
    ``k``-th column of ``U`` above the diagonal."""
    n = W.shape[-2]
    W, weights = torch.broadcast_tensors(W, weights.unsqueeze(-2))
    weights = weights[..., 0, :]
    columns: list[Tensor] = [W.new_empty(0)] * n
    diagonal: list[Tensor] = [W.new_empty(0)] * n
    for k in range(n - 1, -1, -1):
        v = W[..., k, :]
        weighted = v * weights
        d_k = (v * weighted).sum(-1)
        diagonal[k] = d_k
        # A row of zero weight (a state with neither variance nor noise) couples to nothing.
        safe = torch.where(d_k > 0, d_k, 1.0)
        u = torch.where(d_k.unsqueeze(-1) > 0, matvec(W[..., :k, :], weighted) / safe[..., None], 0)
        W = torch.cat([W[..., :k, :] - u.unsqueeze(-1) * v.unsqueeze(-2), W[..., k:, :]], dim=-2)
        one = torch.ones_like(d_k).unsqueeze(-1)
        columns[k] = torch.cat([u, one, u.new_zeros(*u.shape[:-1], n - k - 1)], dim=-1)
    return torch.stack(columns, dim=-1), torch.stack(diagonal, dim=-1)


def _bierman(U: Tensor, d: Tensor, H: Tensor, variances: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Bierman's measurement update, the rows of ``H [..., m, n]`` one scalar measurement at a
    time with independent noise ``variances [..., m]``: the posterior ``U``, ``d`` and the gain
    ``K [..., n, m]`` that maps the innovations ``e`` to ``x⁺ − x⁻``.

    Per component (Bierman 1977; ``bierman.m`` of Grewal and Andrews, Ch. 7): ``f = Uᵀh``,
    ``b = D f``, ``α_0 = r``; for ``j = 1..n``: ``α_j = α_{j−1} + f_j b_j``, ``d_j ← d_j
    α_{j−1}/α_j``, ``λ = −f_j/α_{j−1}``, ``U_ij ← U_ij + b_i λ`` and ``b_i ← b_i + b_j U_ij``
    (old ``U_ij``) for ``i < j``; the scalar gain is ``k = b/α_n``. The sequence applies
    ``x ← x + k (e_i − hᵀ(x − x⁻))``, so the vector gain accumulates as ``G ← G + k (ε_iᵀ −
    hᵀG)``."""
    n, m = U.shape[-1], H.shape[-2]
    lead = torch.broadcast_shapes(U.shape[:-2], H.shape[:-2], variances.shape[:-1])
    columns = list(U.expand(*lead, n, n).unbind(-1))
    diagonal = list(d.expand(*lead, n).unbind(-1))
    H = H.expand(*lead, m, n)
    variances = variances.expand(*lead, m)
    G = U.new_zeros(*lead, n, m)
    for i in range(m):
        h = H[..., i, :]
        f = matvec(torch.stack(columns, dim=-1).mT, h)
        b = f * torch.stack(diagonal, dim=-1)
        alpha = variances[..., i]
        for j in range(n):
            before = alpha
            alpha = before + f[..., j] * b[..., j]
            diagonal[j] = diagonal[j] * before / alpha
            if j == 0:
                continue
            lam = -f[..., j] / before
            old = columns[j][..., :j]
            columns[j] = torch.cat([old + b[..., :j] * lam.unsqueeze(-1), columns[j][..., j:]], -1)
            b = torch.cat([b[..., :j] + b[..., j : j + 1] * old, b[..., j:]], dim=-1)
        k = b / alpha.unsqueeze(-1)
        unit = G.new_zeros(m)
        unit[i] = 1.0
        G = G + k.unsqueeze(-1) * (unit - matvec(G.mT, h)).unsqueeze(-2)
    return torch.stack(columns, dim=-1), torch.stack(diagonal, dim=-1), G


def _weights(d: Tensor, noise: Tensor) -> Tensor:
    """The weights ``[d, 1, ..., 1]`` of a UD array ``[· U, noise]`` (``noise [..., n, q]``)."""
    ones = noise.new_ones(*noise.shape[:-2], noise.shape[-1])
    lead = torch.broadcast_shapes(d.shape[:-1], ones.shape[:-1])
    return torch.cat([d.expand(*lead, -1), ones.expand(*lead, -1)], dim=-1)


def _is_diagonal(A: Tensor) -> bool:
    return not bool((A - torch.diag_embed(A.diagonal(dim1=-2, dim2=-1))).any())


class Full(NamedTuple):
    """``"conventional"``: the covariance itself, ``P⁺ = (I − KH)P⁻`` (Eq. (9)), not symmetrised.

    For the SVSF, whose gain is not the Kalman gain, ``(I − KH)P⁻`` is the right side of Eq. (28)
    of Chen et al. 2020 as printed: it is not the covariance of the SVSF's estimate (the Joseph
    form, the left side, is); offered to reproduce the printed form and to compare with it."""

    P: Tensor

    @classmethod
    def of(cls, P: Tensor) -> Full:
        return cls(P)

    def full(self) -> Tensor:
        return self.P

    def positive_definite(self) -> Tensor:
        """``[...]``: every eigenvalue of ``P`` (symmetrised) positive."""
        return torch.linalg.eigvalsh(symmetrize(self.P)).amin(-1) > 0

    def predict(self, F: Tensor, Q: Tensor) -> Full:
        return Full(F @ self.P @ F.mT + Q)  # Eq. (6)

    def kalman_update(self, H: Tensor, R: Tensor, S: Tensor) -> tuple[Tensor, Full]:
        K = right_psd_solve(self.P @ H.mT, S)  # Eq. (8), through the Cholesky factor of S
        return K, self.gain_update(K, H, R)

    def gain_update(self, K: Tensor, H: Tensor, R: Tensor) -> Full:
        return Full((_eye_like(self.P) - K @ H) @ self.P)  # Eq. (9)


class Cholesky(NamedTuple):
    """``"sqrt"``: ``P = S Sᵀ`` with ``S`` lower triangular, nonnegative diagonal."""

    S: Tensor

    @classmethod
    def of(cls, P: Tensor) -> Cholesky:
        return cls(cholesky(P))

    def full(self) -> Tensor:
        return symmetrize(self.S @ self.S.mT)

    def positive_definite(self) -> Tensor:
        """``[...]``: ``S`` nonsingular (its pivots positive), so ``SSᵀ`` is, whatever rounding
        does to eigenvalues below eps when ``P`` is formed."""
        return (self.S.diagonal(dim1=-2, dim2=-1) > 0).all(-1)

    def predict(self, F: Tensor, Q: Tensor) -> Cholesky:
        return Cholesky(_lower_factor(_rows((F @ self.S).mT, cholesky(Q).mT)))

    def kalman_update(self, H: Tensor, R: Tensor, S: Tensor) -> tuple[Tensor, Cholesky]:
        m = H.shape[-2]
        C, HS = _batched(cholesky(R), H @ self.S)
        top = torch.cat([C, HS], dim=-1)
        bottom = torch.cat(_batched(HS.new_zeros(*HS.shape[:-2], *HS.mT.shape[-2:]), self.S), -1)
        post = _lower_factor(torch.cat([top, bottom], dim=-2).mT)  # Morf-Kailath
        X, Y = post[..., :m, :m], post[..., m:, :m]
        K = torch.linalg.solve_triangular(X, Y, upper=False, left=False)  # Y X⁻¹
        return K, Cholesky(post[..., m:, m:])

    def gain_update(self, K: Tensor, H: Tensor, R: Tensor) -> Cholesky:
        A = _eye_like(self.S) - K @ H
        return Cholesky(_lower_factor(_rows((A @ self.S).mT, (K @ cholesky(R)).mT)))


class UD(NamedTuple):
    """``"ud"``: ``P = U diag(d) Uᵀ`` with ``U`` unit upper triangular, ``d ≥ 0``."""

    U: Tensor
    d: Tensor

    @classmethod
    def of(cls, P: Tensor) -> UD:
        # The upper-triangular C with P = C Cᵀ is the lower Cholesky factor of P with its rows
        # and columns reversed; U = C diag(C)⁻¹, d = diag(C)².
        C = cholesky(P.flip(-2, -1)).flip(-2, -1)
        c = C.diagonal(dim1=-2, dim2=-1)
        return cls(C / c.unsqueeze(-2), c.square())

    def full(self) -> Tensor:
        return symmetrize((self.U * self.d.unsqueeze(-2)) @ self.U.mT)

    def positive_definite(self) -> Tensor:
        """``[...]``: ``d > 0``."""
        return (self.d > 0).all(-1)

    def predict(self, F: Tensor, Q: Tensor) -> UD:
        G = cholesky(Q)
        W = torch.cat(_batched(F @ self.U, G), dim=-1)
        return UD(*_mwgs(W, _weights(self.d, G)))

    def kalman_update(self, H: Tensor, R: Tensor, S: Tensor) -> tuple[Tensor, UD]:
        if _is_diagonal(R) and not (torch.is_grad_enabled() and R.requires_grad):
            # (with a gradient asked of R, its zero off-diagonal entries have one too)
            U, d, K = _bierman(self.U, self.d, H, R.diagonal(dim1=-2, dim2=-1))
            return K, UD(U, d)
        # Correlated noise: measure z' = C⁻¹z (H' = C⁻¹H, R' = I); the gain on z is K' C⁻¹.
        C = cholesky(R)
        white = torch.linalg.solve_triangular(C, H, upper=False)
        U, d, K = _bierman(self.U, self.d, white, torch.ones_like(R[..., 0]))
        return torch.linalg.solve_triangular(C, K, upper=False, left=False), UD(U, d)

    def gain_update(self, K: Tensor, H: Tensor, R: Tensor) -> UD:
        C = cholesky(R)
        A = _eye_like(self.U) - K @ H
        KC = K @ C
        return UD(*_mwgs(torch.cat(_batched(A @ self.U, KC), dim=-1), _weights(self.d, KC)))


class SVD(NamedTuple):
    """``"svd"``: ``P = U diag(d²) Uᵀ`` with ``U`` orthogonal, ``d`` the singular values of the
    covariance's square root (K-SVD, Sec. 4)."""

    U: Tensor
    d: Tensor

    @classmethod
    def of(cls, P: Tensor) -> SVD:
        # P = L Lᵀ and Lᵀ = W diag(d) Vᵀ give P = V diag(d²) Vᵀ (Eq. (17), Algorithm 1's start).
        return cls(*right_svd(cholesky(P).mT))

    def full(self) -> Tensor:
        return symmetrize((self.U * self.d.square().unsqueeze(-2)) @ self.U.mT)

    def positive_definite(self) -> Tensor:
        """``[...]``: every singular value of the root positive."""
        return (self.d > 0).all(-1)

    def predict(self, F: Tensor, Q: Tensor) -> SVD:
        root = (F @ self.U) * self.d.unsqueeze(-2)  # F U D: P⁻ = (FUD)(FUD)ᵀ + Q, Eq. (18)
        return SVD(*right_svd(_rows(root.mT, cholesky(Q).mT)))  # Eqs. (20)-(23)

    def kalman_update(self, H: Tensor, R: Tensor, S: Tensor) -> tuple[Tensor, SVD]:
        C = cholesky(R)  # R = C Cᵀ, R⁻¹ = L Lᵀ with L = C⁻ᵀ (Eq. (31))
        LH = torch.linalg.solve_triangular(C, H, upper=False)  # Lᵀ H
        V, s = right_svd(_rows(LH @ self.U, torch.diag_embed(1.0 / self.d)))  # Eqs. (32)-(34)
        U, d = self.U @ V, 1.0 / s  # Eqs. (37)-(38)
        # K = U⁺ D⁺² U⁺ᵀ Hᵀ L Lᵀ (Eq. (43)): (U⁺ D⁺² U⁺ᵀ (LᵀH)ᵀ) C⁻¹.
        PHtL = (U * d.square().unsqueeze(-2)) @ (U.mT @ LH.mT)
        K = torch.linalg.solve_triangular(C, PHtL, upper=False, left=False)
        return K, SVD(U, d)

    def gain_update(self, K: Tensor, H: Tensor, R: Tensor) -> SVD:
        A = _eye_like(self.U) - K @ H
        root = (A @ self.U) * self.d.unsqueeze(-2)
        return SVD(*right_svd(_rows(root.mT, (K @ cholesky(R)).mT)))


#: A covariance in one of this module's forms.
Factor = Full | Cholesky | UD | SVD

#: The factor type of each form (``"joseph"``: none, the filters update ``P`` itself).
FACTORS: dict[str, type[Full] | type[Cholesky] | type[UD] | type[SVD]] = {
    "conventional": Full,
    "sqrt": Cholesky,
    "ud": UD,
    "svd": SVD,
}


class Carried(NamedTuple):
    """A factor carried in a :class:`~torchsvs.types.FilterState` beside the covariance it stands
    for: a state whose ``cov`` was replaced (an IMM's mixing, a caller's edit) is factored anew."""

    factor: Factor
    cov: Tensor


def resume(carried: Any, cov: Tensor, dtype: torch.dtype, form: str) -> Factor | None:
    """The factor a state carries for ``cov``, if it is still that of ``cov`` in ``form`` and
    ``dtype``; else ``None`` (then ``cov`` is factored)."""
    kind = FACTORS.get(form)
    if kind is None or not isinstance(carried, Carried) or carried.cov is not cov:
        return None
    return carried.factor if cov.dtype == dtype and isinstance(carried.factor, kind) else None

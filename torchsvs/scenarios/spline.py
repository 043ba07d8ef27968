r"""Natural cubic splines, chord-length curves through points, and their arc-length form.

The curve roads of Zhang & Zhou (2022, Sec. 5.3, Eq. (48)) are cubic splines through supporting
points :math:`P_i = (p_{x,i}, p_{y,i})`, ``i = 1..ρ``, parameterised by the chord length

.. math::
    u_1 = 0,\qquad u_{i+1} = u_i + \lVert P_{i+1} - P_i \rVert,

one natural cubic spline per axis (Eqs. (48)-(49), rebuilt): on the ``i``-th segment
:math:`u \in [u_i, u_{i+1}]`, :math:`h_i = u_{i+1} - u_i`,

.. math::
    l_x(u) = a_{x,i} + b_{x,i}(u - u_i) + c_{x,i}(u - u_i)^2 + d_{x,i}(u - u_i)^3,

    a_{x,i} = p_{x,i},\quad b_{x,i} = \frac{p_{x,i+1} - p_{x,i}}{h_i}
        - \frac{h_i (2 M_{x,i} + M_{x,i+1})}{6},\quad
    c_{x,i} = \frac{M_{x,i}}{2},\quad d_{x,i} = \frac{M_{x,i+1} - M_{x,i}}{6 h_i},

where the second derivatives :math:`M_{x,i}` solve the tridiagonal system
:math:`h_{i-1} M_{i-1} + 2(h_{i-1} + h_i) M_i + h_i M_{i+1} = 6\big(\frac{p_{i+1} - p_i}{h_i}
- \frac{p_i - p_{i-1}}{h_{i-1}}\big)`, ``i = 2..ρ-1``, with the natural end conditions
:math:`M_1 = M_\rho = 0` (de Boor 1978, Ch. IV). The same for ``y``.

Chord length only approximates arc length; the target moves by arc length ``s`` (its trajectory
shape independent of its speed), so the curve is reparameterised: ``s(u) = ∫₀ᵘ |l'(v)| dv`` is
tabulated on a dense grid (5-point Gauss-Legendre per grid cell), ``u(s)`` is interpolated
linearly in that table and refined by Newton steps on ``s(u) − s`` (each evaluating the integral
from the grid point below exactly by Gauss-Legendre), so positions at given arc lengths are
accurate to rounding.

References:
    de Boor, "A Practical Guide to Splines", Springer 1978 · Zhang Zhuanhua, Zhou Gongjian,
    J. Syst. Eng. Electron. 33(5), 2022, Sec. 5.3 (its ref. [28] for the coefficients).
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor

# 5-point Gauss-Legendre nodes and weights on [-1, 1].
_GL_NODES = (
    -0.9061798459386640,
    -0.5384693101056831,
    0.0,
    0.5384693101056831,
    0.9061798459386640,
)
_GL_WEIGHTS = (
    0.2369268850561891,
    0.4786286704993665,
    0.5688888888888889,
    0.4786286704993665,
    0.2369268850561891,
)


class NaturalCubicSpline:
    """Natural cubic spline interpolation of ``values [K, d]`` at increasing ``knots [K]``
    (float64), in the power form of Eq. (49) (module docstring).

    Attributes:
        knots: ``[K]``.
        coefficients: ``[K-1, 4, d]``: ``a, b, c, d`` of each segment.
    """

    def __init__(
        self, knots: Tensor | Sequence[float], values: Tensor | Sequence[Sequence[float]]
    ) -> None:
        knots = torch.as_tensor(knots, dtype=torch.float64)
        values = torch.as_tensor(values, dtype=torch.float64)
        if values.ndim == 1:
            values = values.unsqueeze(-1)
        if knots.ndim != 1 or knots.shape[0] < 2 or values.shape[0] != knots.shape[0]:
            raise ValueError(
                f"knots: expected [K] (K ≥ 2) matching values [K, d], got {tuple(knots.shape)} "
                f"and {tuple(values.shape)}"
            )
        h = knots.diff()
        if not bool((h > 0).all()):
            raise ValueError("knots: expected strictly increasing values")
        K = knots.shape[0]
        slopes = values.diff(dim=0) / h.unsqueeze(-1)  # [K-1, d]
        M = values.new_zeros(values.shape)
        if K > 2:
            A = torch.zeros(K - 2, K - 2, dtype=torch.float64)
            idx = torch.arange(K - 2)
            A[idx, idx] = 2.0 * (h[:-1] + h[1:])
            A[idx[1:], idx[:-1]] = h[1:-1]
            A[idx[:-1], idx[1:]] = h[1:-1]
            M[1:-1] = torch.linalg.solve(A, 6.0 * slopes.diff(dim=0))
        hh = h.unsqueeze(-1)
        a = values[:-1]
        b = slopes - hh * (2.0 * M[:-1] + M[1:]) / 6.0
        c = M[:-1] / 2.0
        d = (M[1:] - M[:-1]) / (6.0 * hh)
        self.knots = knots
        self.second_derivatives = M
        self.coefficients = torch.stack([a, b, c, d], dim=1)

    def _segment(self, u: Tensor) -> tuple[Tensor, Tensor]:
        i = torch.searchsorted(self.knots, u.contiguous(), right=True) - 1
        i = i.clamp(0, self.knots.shape[0] - 2)
        return i, (u - self.knots[i]).unsqueeze(-1)

    def __call__(self, u: Tensor, derivative: int = 0) -> Tensor:
        """The spline (or its first or second ``derivative``) at ``u [...]``: ``[..., d]``;
        outside the knots, the end segments' cubics continue."""
        u = torch.as_tensor(u, dtype=torch.float64)
        i, t = self._segment(u)
        a, b, c, d = self.coefficients[i].unbind(-2)
        if derivative == 0:
            return a + t * (b + t * (c + t * d))
        if derivative == 1:
            return b + t * (2.0 * c + 3.0 * t * d)
        if derivative == 2:
            return 2.0 * c + 6.0 * t * d
        raise ValueError(f"derivative: expected 0, 1 or 2, got {derivative!r}")


class ArcLengthSpline:
    r"""A planar curve through ``points [K, 2]``: natural cubic splines in the chord length
    (Eq. (48)), reparameterised by arc length (module docstring).

    Args:
        points: supporting points ``[K, 2]`` (m), consecutive points distinct.
        cells: grid cells per segment of the arc-length table.

    Attributes:
        spline: the chord-length spline ``l(u)`` (:class:`NaturalCubicSpline`).
        chord_knots: ``u_i`` of the points ``[K]``.
        arc_knots: arc length ``s_i`` at the points ``[K]``.
        length: total arc length (m).
    """

    def __init__(self, points: Tensor | Sequence[Sequence[float]], cells: int = 256) -> None:
        points = torch.as_tensor(points, dtype=torch.float64)
        if points.ndim != 2 or points.shape[-1] != 2 or points.shape[0] < 2:
            raise ValueError(f"points: expected shape [K, 2] with K ≥ 2, got {tuple(points.shape)}")
        chords = (points.diff(dim=0)).norm(dim=-1)
        if not bool((chords > 0).all()):
            raise ValueError("points: consecutive supporting points must differ")
        if not (isinstance(cells, int) and cells >= 1):
            raise ValueError(f"cells: expected a positive integer, got {cells!r}")
        self.points = points
        self.chord_knots = torch.cat([chords.new_zeros(1), chords.cumsum(0)])
        self.spline = NaturalCubicSpline(self.chord_knots, points)
        # Dense table of s(u): `cells` equal cells per segment.
        frac = torch.linspace(0.0, 1.0, cells + 1, dtype=torch.float64)[:-1]
        u0, h = self.chord_knots[:-1], chords
        grid = (u0.unsqueeze(-1) + frac * h.unsqueeze(-1)).reshape(-1)
        self.grid = torch.cat([grid, self.chord_knots[-1:]])
        increments = self._integral(self.grid[:-1], self.grid[1:])
        self.grid_arc = torch.cat([increments.new_zeros(1), increments.cumsum(0)])
        self.arc_knots = self.grid_arc[::cells].clone()
        self.length = float(self.grid_arc[-1])

    def _speed(self, u: Tensor) -> Tensor:
        """``|l'(u)|``, the rate of arc length per chord length."""
        return self.spline(u, derivative=1).norm(dim=-1)

    def _integral(self, lo: Tensor, hi: Tensor) -> Tensor:
        """``∫_lo^hi |l'(v)| dv`` by 5-point Gauss-Legendre (both within one segment)."""
        mid, half = (hi + lo) / 2.0, (hi - lo) / 2.0
        total = torch.zeros_like(mid)
        for node, weight in zip(_GL_NODES, _GL_WEIGHTS, strict=True):
            total = total + weight * self._speed(mid + half * node)
        return half * total

    def chord_at(self, s: Tensor, newton_steps: int = 3) -> Tensor:
        """Chord parameter ``u`` of arc lengths ``s [...]`` in ``[0, length]``."""
        s = torch.as_tensor(s, dtype=torch.float64)
        if bool((s < -1e-9).any()) or bool((s > self.length + 1e-9).any()):
            raise ValueError(
                f"s: expected arc lengths in [0, {self.length:.3f}] m, got "
                f"[{float(s.min()):.3f}, {float(s.max()):.3f}]"
            )
        flat = s.reshape(-1).clamp(0.0, self.length)
        j = (torch.searchsorted(self.grid_arc, flat, right=True) - 1).clamp(
            0, self.grid.shape[0] - 2
        )
        s0, s1 = self.grid_arc[j], self.grid_arc[j + 1]
        u0, u1 = self.grid[j], self.grid[j + 1]
        u = u0 + (flat - s0) / (s1 - s0) * (u1 - u0)
        for _ in range(newton_steps):
            u = u - (s0 + self._integral(u0, u) - flat) / self._speed(u)
        return u.reshape(s.shape)

    def position(self, s: Tensor) -> Tensor:
        """Points ``[..., 2]`` at arc lengths ``s [...]``."""
        return self.spline(self.chord_at(s))

    def direction(self, s: Tensor) -> Tensor:
        """Unit tangents ``[..., 2]`` (direction of travel) at arc lengths ``s [...]``."""
        tangent = self.spline(self.chord_at(s), derivative=1)
        return tangent / tangent.norm(dim=-1, keepdim=True)

    def curvature(self, s: Tensor) -> Tensor:
        """Signed curvature ``[...]`` (1/m, positive to the left) at arc lengths ``s [...]``."""
        u = self.chord_at(s)
        d1, d2 = self.spline(u, derivative=1), self.spline(u, derivative=2)
        cross = d1[..., 0] * d2[..., 1] - d1[..., 1] * d2[..., 0]
        return cross / d1.norm(dim=-1) ** 3

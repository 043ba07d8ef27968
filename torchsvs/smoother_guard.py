"""An IMM smoother's guard in ``torchsvs track``: each track keeps its smoothed or its filtered
pass, whichever SURE rates lower (:func:`smoothed_or_filtered`, called by
:func:`torchsvs.estimating.estimate_group`)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import torch
from torch import Tensor

from torchsvs.accuracy import Probe, RiskTerms, risk_terms
from torchsvs.error_references import LinearReference, SelfReference


def smoothed_or_filtered(
    out: Any,
    rerun: Callable[[Tensor], Any],
    z: Tensor,
    meas_std: Tensor,
    probe: Probe,
    noise_range: tuple[list[float], list[float]] | None = None,
    control: LinearReference | SelfReference | None = None,
) -> tuple[Any, RiskTerms, np.ndarray]:
    """Each track's smoothed pass of ``out`` (a result with a ``filtered`` pass: the IMM's
    smoother), or its filter pass where that has the lower SURE (:mod:`torchsvs.accuracy`, both
    from one run ``rerun`` on the ``probe``'s measurements; ``control``: the estimate's control
    variate, :func:`~torchsvs.error_references.reference_for`): a guard where the smoother's
    backward pass fails. Kim's smoother links a mode's estimates by the mode's own dynamics,
    and on tracks whose motion at their report times neither mode follows (gliders and survey
    aircraft at 7-33 s, speed jumps in the record) the IMM's fixed-lag smoother was 1.25x the
    raw measurements (the filter 1.01x) on the recorded-tracks benchmark's irregular set, while
    it was 0.31-0.57x raw elsewhere. Where the noise was read off the data, the smoother is kept
    only where it is the better at both ends of the interval ``noise_range`` too (SURE is
    linear in the noise variance; :data:`~torchsvs.fitting.defaults.GUARD_ERRORS` standard errors
    wide in ``track``):
    motion the report times cannot resolve reads as noise (71.8 m for 50 on that set), and the
    divergence term, weighted by that noise, then favours the smoother, which follows the data
    less. Returns the result with the chosen passes' ``mean``
    and ``cov`` per track (the other fields the smoother's), their risk terms, and ``[B]`` which
    tracks fell back to the filter."""
    shifted = rerun(probe.measurements)  # one probed run serves both passes

    def terms_of(pick: Callable[[Any], Tensor], filtered: bool) -> RiskTerms:
        reference = None if control is None else control.reference(out, filtered)
        return risk_terms(
            lambda _: pick(shifted)[..., 0::2],  # (the probe's measurements: run above)
            z,
            pick(out)[..., 0::2],
            meas_std,
            None,
            reference=reference,
            probe=probe,
        )

    smooth = terms_of(lambda result: result.mean, False)
    filt = terms_of(lambda result: result.filtered.mean, True)
    levels = [meas_std.double().square().tolist(), *(noise_range or ())]
    B = z.shape[0]
    fall_back = np.zeros(B, dtype=bool)
    for r in levels:  # each track's estimated error (NaN: nothing observed, no fallback)
        fall_back |= filt.per_track(r, B)[0] < smooth.per_track(r, B)[0]
    back = torch.from_numpy(fall_back)
    mean = torch.where(back[:, None, None], out.filtered.mean, out.mean)
    cov = out.cov
    if cov is not None and out.filtered.cov is not None:
        cov = torch.where(back[:, None, None, None], out.filtered.cov, cov)
    chunks = fall_back[smooth.track][:, None]  # the two passes' chunks are the same
    terms = RiskTerms(
        np.where(chunks, filt.residual, smooth.residual),
        np.where(chunks, filt.divergence, smooth.divergence),
        smooth.count,
        smooth.track,
    )
    return out._replace(mean=mean, cov=cov), terms, fall_back

"""An SVSF and a KF as the modes of one IMM: the KF on the SVSF's artificial measurement
(``ArtificialKalmanFilter``), so the two innovation likelihoods score the same thing."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import torchsvs as ts
from tests.conftest import assert_close, atc_batch
from tests.reference import svs_numpy as ref

PSI = [500.0, 600.0, 500.0, 600.0]


def test_artificial_kalman_filter_is_the_kf_on_the_pseudo_measurements():
    """Against the NumPy KF run on ``y = [z1, v1, z2, v2]`` with ``H = I`` and Eq. (51)'s
    derived noise (as the SVSF's artificial-velocity reference test builds them)."""
    sc = atc_batch(2, seed=4)
    z = sc.z.clone()
    z[0, 7, 1] = float("nan")
    kf = ts.ArtificialKalmanFilter(sc.model, ts.FiniteDifferenceVelocity(bridge_gaps=False))
    out = kf(z, sc.x0, sc.P0)
    r_pos = sc.model.meas_cov()[0, 0].item()
    R_y = np.kron(np.eye(2), np.array([[r_pos, r_pos], [r_pos, 2 * r_pos]]))  # dt = 1
    F, Q = sc.model.transition().numpy(), sc.model.process_noise().numpy()
    for b in range(2):
        y = ref.finite_difference_velocity(z[b].numpy(), 1.0)
        r = ref.kalman_filter(y, sc.x0.numpy(), sc.P0.numpy(), F, np.eye(4), Q, R_y)
        for key in ("mean", "cov", "pred_mean", "pred_cov", "innovation"):
            assert_close(getattr(out, key)[b], r[key], msg=key)
    assert out.innovation.shape[-1] == 4 and out.log_likelihood is not None


def test_artificial_kalman_filter_step_by_step_equals_the_run():
    sc = atc_batch(2, seed=5)
    kf = ts.ArtificialKalmanFilter(sc.model)  # "auto": finite-difference velocity
    whole = kf(sc.z, sc.x0, sc.P0)
    state = kf.init(sc.x0, sc.P0)
    means = []
    for t in range(20):
        state, out = kf.step(state, sc.z[:, t])
        means.append(out.mean)
    assert_close(torch.stack(means, 1), whole.mean[:, :20])


def test_svsf_and_kf_on_one_measurement_mix_in_an_imm():
    sc = ts.scenarios.complex_scenario(8, torch.Generator().manual_seed(1))
    fd = ts.FiniteDifferenceVelocity()
    svsf = ts.SVSF(sc.model, psi=PSI, gamma=0.1, artificial=fd)
    imm = ts.IMM([svsf, ts.ArtificialKalmanFilter(sc.model, fd)], [[0.95, 0.05], [0.05, 0.95]])
    with torch.no_grad():
        out = imm(sc.z, sc.x0, sc.P0)
    assert torch.isfinite(out.mean).all()
    mu = out.mode_probs[..., 0]
    assert 0.05 < float(mu.mean()) < 0.95 and float(mu.std()) > 0.05  # neither mode takes all
    # A plain KF measures z, the SVSF [z, finite-difference velocity]: not comparable.
    with pytest.raises(ValueError, match="^filters: the modes' correctors measure different"):
        ts.IMM([svsf, ts.KalmanFilter(sc.model)], [[0.95, 0.05], [0.05, 0.95]])(sc.z, sc.x0, sc.P0)


def test_artificial_kalman_filter_needs_an_artificial_measurement():
    with pytest.raises(ValueError, match="^artificial: 'auto' finds no artificial measurement"):
        eye = torch.eye(2, dtype=torch.float64)
        ts.ArtificialKalmanFilter(ts.models.LinearGaussian(eye, eye, eye, eye))
    with pytest.raises(TypeError, match="^artificial: expected 'auto' or a callable"):
        ts.ArtificialKalmanFilter(ts.models.ConstantVelocity(), artificial=3)


def test_reduced_experiment_imm_beats_each_mode_and_writes_its_report(tmp_path):
    """``experiments/imm_svsf_kf.py`` on 30 runs: the IMM's velocity beats the SVSF's and both
    KFs', its positions the KFs'; the report and figures are written."""
    from experiments.imm_svsf_kf import MAIN, figures, imm_name, report, run

    res = run(runs=30, seed=2)
    imm, svsf = res.rows[imm_name(MAIN)][0], res.rows["SVSF"][0]
    for kf in ("KF", "KF on [z, FD velocity]"):
        assert all(a < b for a, b in zip(imm, res.rows[kf][0], strict=True))
    assert imm[1] < svsf[1] and imm[3] < svsf[3]
    mu = res.mode_probs[imm_name(MAIN)]
    assert float(((mu > 0.01) & (mu < 0.99)).double().mean()) > 0.8
    assert res.likelihood_check < 1e-12
    names = figures(res, tmp_path)
    text = report(res)
    assert all((tmp_path / n).exists() for n in names) and "## Accumulative RMSE" in text

"""Training: losses, the data module, a short fit, checkpoints, the CLI config, DDP (slow)."""

from __future__ import annotations

import subprocess
import sys
from functools import partial
from pathlib import Path

import lightning as L
import pytest
import torch

import torchsvs as ts
from tests.conftest import assert_close
from torchsvs.fitting.batches import batch_loss
from torchsvs.fitting.losses import stein_risk
from torchsvs.scenarios import ManeuverRanges
from torchsvs.training import (
    EstimatorModule,
    ManeuveringTargetDataModule,
    config_path,
    shipped_configs,
)
from torchsvs.training.cli import main as cli_main
from torchsvs.training.quiet import tool_trainer

pytestmark = pytest.mark.filterwarnings(
    "ignore:.*does not have many workers.*", "ignore:.*LeafSpec.*", "ignore:.*litlogger.*"
)
RANGES = ManeuverRanges(
    steps=60, speed=(80.0, 200.0), segment_duration=(10.0, 30.0), meas_std=(50.0, 50.0)
)


def _data(**kw) -> ManeuveringTargetDataModule:
    args = dict(batch_size=16, train_batches=6, val_batches=2, test_batches=2, seed=1)
    args.update(kw)
    return ManeuveringTargetDataModule(RANGES, prior_std=(30.0, 10.0), **args)


def _svss(psi: float = 10.0) -> ts.SVSS:
    model = ts.models.ConstantVelocity(dt=1.0, q=1.0, r=50.0**2)
    return ts.SVSS(ts.SVSF(model, psi=[psi, psi], gamma=0.1, artificial=None))


def _trainer(tmp_path, epochs: int = 2, **kw) -> L.Trainer:
    return tool_trainer(max_epochs=epochs, default_root_dir=tmp_path, **kw)


def test_data_module_splits_are_seeded_and_disjoint():
    a, b = _data(), _data()
    a.setup("fit")
    b.setup("fit")
    first, again = a.datasets["train"][0], b.datasets["train"][0]
    assert_close(first.z, again.z, atol=0, rtol=0)
    assert first.z.shape == (16, 60, 2) and first.truth.shape == (16, 60, 4)
    assert first.x0.shape == (16, 4) and first.P0.shape == (4, 4)
    assert (a.datasets["val"][0].truth - first.truth).abs().max() > 1.0
    hard = _data(outlier_prob=0.05, missing_prob=0.1)
    hard.setup("fit")
    z = hard.datasets["train"][0].z
    assert 0.05 < torch.isnan(z).float().mean() < 0.15
    assert not bool(torch.isnan(hard.datasets["val"][0].z).any())  # hard cases in training only


@pytest.mark.parametrize("loss", ["supervised", "sure", "nll", "prediction"])
def test_losses_and_gradients_finite_on_hard_batches(loss):
    data = _data(outlier_prob=0.05, outlier_scale=20.0, missing_prob=0.1)
    data.setup("fit")
    batch = data.datasets["train"][0]
    batch = batch._replace(z=batch.z.clone())
    batch.z[:, 7] = float("nan")  # an all-missing step
    module = EstimatorModule(_svss(), loss=loss)
    value, _ = batch_loss(module.estimator, batch, loss, module.components, None, module.probes)
    assert bool(torch.isfinite(value))
    value.backward()
    grads = [p.grad for p in module.parameters()]
    assert all(g is not None and bool(torch.isfinite(g).all()) for g in grads)


def test_sure_estimates_the_true_mse_without_truth():
    sc = ts.scenarios.atc_scenario(100, torch.Generator().manual_seed(4))
    H, R = sc.model.meas_matrix(), sc.model.meas_cov()
    for psi in (100.0, 1000.0, 3000.0):
        est = ts.SVSS(ts.SVSF(sc.model, psi=psi, gamma=0.1, artificial=None))
        with torch.no_grad():
            out = est(sc.z, sc.x0, sc.P0)
            rerun = partial(est, x0=sc.x0, P0=sc.P0)
            risk = stein_risk(rerun, out, sc.z, H, R, torch.Generator().manual_seed(0))
        true = ((out.mean[..., [0, 2]] - sc.truth[..., [0, 2]]).square() / R.diagonal()).mean()
        assert abs(risk.item() / true.item() - 1) < 0.05


@pytest.mark.parametrize("loss", ["supervised", "sure"])
def test_training_lowers_the_error(tmp_path, loss):
    data = _data()
    module = EstimatorModule(_svss(psi=100.0), loss=loss, lr=0.3)
    trainer = _trainer(tmp_path, epochs=4)
    before = trainer.validate(module, data, verbose=False)[0]["val_rmse"]
    trainer.fit(module, data)
    after = trainer.validate(module, data, verbose=False)[0]["val_rmse"]
    assert after < 0.85 * before, (before, after)
    svsf = module.estimator.filter
    assert bool((svsf.psi > 100.0).all()) and 0.0 < svsf.gamma.item() < 1.0


def test_checkpoint_reloads_an_identical_model(tmp_path):
    data = _data()
    module = EstimatorModule(_svss(), loss="supervised", lr=0.2)
    trainer = _trainer(tmp_path, epochs=1, enable_checkpointing=True)
    trainer.fit(module, data)
    path = (
        trainer.checkpoint_callback.best_model_path or trainer.checkpoint_callback.last_model_path
    )
    assert Path(path).is_file()
    loaded = EstimatorModule.load_from_checkpoint(path, estimator=_svss())
    for (name, p), (_, q) in zip(
        module.state_dict().items(), loaded.state_dict().items(), strict=True
    ):
        assert_close(p, q, atol=0, rtol=0, msg=name)
    batch = data.datasets["val"][0]
    with torch.no_grad():
        assert_close(
            loaded(batch.z, batch.x0, batch.P0).mean,
            module(batch.z, batch.x0, batch.P0).mean,
            atol=0,
            rtol=0,
        )
    assert loaded.loss_name == "supervised" and loaded.lr == 0.2


@pytest.mark.parametrize("config", ["atc_svss", "complex_svss.yaml"])
def test_cli_configs_build(config):
    """The shipped configs, by name (with or without .yaml), from the installed package."""
    cli = cli_main(["--config", config], run=False)
    (read,) = cli.config.config
    assert Path(read.absolute) == config_path(config)
    assert config_path(config).parent == Path(ts.training.__file__).parent / "configs"
    est = cli.model.estimator
    assert isinstance(est, ts.SVSS) and isinstance(est.filter, ts.SVSF)
    assert_close(est.filter.psi.detach(), torch.full_like(est.filter.psi.detach(), 100.0))
    assert cli.datamodule.batch_size == 64


def test_shipped_config_names_resolve_and_unknown_names_fail_clearly(capsys):
    assert shipped_configs() == ["atc_svss", "complex_svss"]
    for name in shipped_configs():
        assert config_path(name) == config_path(f"{name}.yaml") and config_path(name).is_file()
    with pytest.raises(ValueError, match="'atc_svs'; shipped configs: atc_svss, complex_svss$"):
        config_path("atc_svs")
    with pytest.raises(SystemExit) as exit_info:
        cli_main(["--config", "atc_svs"], run=False)
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    assert "--config: 'atc_svs' is neither a file nor a shipped config" in err
    assert "shipped configs: atc_svss, complex_svss" in err


def test_a_config_file_is_read_as_a_path_before_a_shipped_name(monkeypatch, tmp_path):
    text = config_path("atc_svss").read_text().replace("batch_size: 64", "batch_size: 7")
    (tmp_path / "atc_svss.yaml").write_text(text)
    monkeypatch.chdir(tmp_path)
    assert cli_main(["--config", "atc_svss.yaml"], run=False).datamodule.batch_size == 7
    assert cli_main(["--config", "atc_svss"], run=False).datamodule.batch_size == 64


def test_fit_help_names_the_shipped_configs(capsys):
    from torchsvs import cli

    with pytest.raises(SystemExit) as exit_info:
        cli.main(["fit", "--help"])
    assert exit_info.value.code == 0
    assert "shipped with torchsvs: atc_svss, complex_svss" in " ".join(
        capsys.readouterr().out.split()
    )


def test_bad_module_arguments():
    with pytest.raises(ValueError, match="^loss: expected one of"):
        EstimatorModule(_svss(), loss="mae")
    frozen = ts.SVSS(
        ts.SVSF(ts.models.ConstantVelocity(), psi=1.0, gamma=0.1, learn=False, artificial=None)
    )
    with pytest.raises(ValueError, match="^estimator: has no learnable parameter"):
        EstimatorModule(frozen)


def _fit_psi(tmp_path: Path, devices: int) -> list[float]:
    out = tmp_path / f"psi_{devices}.pt"
    strategy = "ddp" if devices > 1 else "auto"
    code = f"""
import sys, torch
from torchsvs.training.cli import main
cli = main(["--config", "atc_svss",
    "--trainer.max_epochs", "4", "--data.train_batches", "{8 * devices}", "--data.batch_size", "32",
    "--data.val_batches", "1", "--trainer.devices", "{devices}", "--trainer.strategy", "{strategy}",
    "--trainer.enable_progress_bar", "false", "--trainer.logger", "false",
    "--trainer.callbacks", "null", "--trainer.enable_checkpointing", "false"])
if cli.trainer.global_rank == 0:
    torch.save(cli.model.estimator.filter.psi.detach(), {str(out)!r})
"""
    # A script file, not `python -c`: Lightning's DDP launcher re-runs the script per process.
    script = tmp_path / f"fit_{devices}.py"
    script.write_text(code)
    subprocess.run([sys.executable, str(script)], check=True, cwd=tmp_path, timeout=900)
    return torch.load(out).tolist()


@pytest.mark.slow
def test_ddp_on_two_cpu_processes_learns_the_same_psi(tmp_path):
    """Two gloo processes, each with half of twice the batches: the same number of optimiser
    steps as one process, each averaging two batches' gradients."""
    single = _fit_psi(tmp_path, 1)
    double = _fit_psi(tmp_path, 2)
    assert all(p > 300.0 for p in double)  # moved far from the 100 m start
    for a, b in zip(single, double, strict=True):
        assert abs(a / b - 1) < 0.25, (single, double)


class _FiniteGradients(L.Callback):
    """Fails the run at the first non-finite loss or gradient."""

    def on_after_backward(self, trainer, module) -> None:
        for name, p in module.named_parameters():
            assert p.grad is not None and bool(torch.isfinite(p.grad).all()), name

    def on_train_batch_end(self, trainer, module, outputs, batch, batch_idx) -> None:
        assert bool(torch.isfinite(outputs["loss"])), batch_idx


@pytest.mark.parametrize("loss", ["supervised", "sure"])
def test_full_run_on_hard_batches_stays_finite(tmp_path, loss):
    data = _data(outlier_prob=0.03, outlier_scale=30.0, missing_prob=0.1)
    module = EstimatorModule(_svss(psi=100.0), loss=loss, lr=0.3)
    _trainer(tmp_path, epochs=2, callbacks=[_FiniteGradients()]).fit(module, data)
    svsf = module.estimator.filter
    assert bool(torch.isfinite(svsf.psi).all()) and bool((svsf.psi > 0).all())
    assert 0.0 <= svsf.gamma.item() < 1.0

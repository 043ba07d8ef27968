"""ψ from a network, trained without truth: does it transfer from one kind of vehicle to another?

The estimator as a layer (issue 29, item 5). A small network reads the normalised innovations
of a Kalman filter pre-pass around each step (a maneuver or a fault shows there as a run of
large innovations) and scales the variable boundary layer's limit ψ per step and axis
(:class:`~torchsvs.filters.VariableBoundarySVSF`: inside the limit the gain is the Kalman gain,
beyond it the prior is inflated). ψ_t acts as an adaptive process noise: a small ψ_t lets the
filter follow the measurements through a maneuver, a large one smooths.

It is trained on recorded tracks with Stein's unbiased risk estimate as the loss
(:func:`~torchsvs.fitting.losses.stein_risk`, in units of the read measurement noise): no truth
enters training, and the probed re-run passes through the network too, so SURE's divergence
counts how ψ_t follows the data. Its features are free of units (innovations in their own
standard deviations), so one network can be tried on any kind of track.

Protocol: the tracks of each set of the recorded benchmark (:mod:`experiments.recorded_sets`)
are split in two halves. The network is trained on the first halves of one kind (or of all
kinds) and scored with the truth on the second halves of every kind. On a half, every estimator
starts from that half's own truth-free settings (noise read off the data, then ``--fit``), as a
user would get them: the Kalman smoother, the SVSS with its fitted constant ψ, and the same SVSS
with the network's ψ_t. Writes ``experiments/results/network_psi.md`` and a figure.

    python -m experiments.network_psi [--epochs 40] [--rows 5000]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import torch
from torch import Tensor, nn
from tqdm.auto import tqdm

from experiments.common import render
from experiments.recorded_sets import build_sets
from torchsvs.accuracy import PROBE_STEP, draw_probe, risk_terms
from torchsvs.accuracy import accuracy as accuracy_of
from torchsvs.datasets.tracks import RecordedTracks, read_tracks, with_prior
from torchsvs.error_references import reference_for
from torchsvs.evaluation import markdown_table
from torchsvs.filters import KalmanFilter
from torchsvs.fitting.batches import batch_loss, recorded_batches
from torchsvs.fitting.defaults import complete_settings
from torchsvs.fitting.tuning import self_tune
from torchsvs.recipes import Settings, make_estimator, make_model
from torchsvs.runs import run_result
from torchsvs.smoothers import SVSS
from torchsvs.step_estimates import centred

#: The sets (kind, σ m) the network is trained and scored on.
SETS = (
    ("own", 10.0),
    ("own", 50.0),
    ("scan10", 50.0),
    ("scan1", 50.0),
    ("taxi", 10.0),
    ("taxi", 50.0),
    ("irregular", 50.0),
    ("turning", 50.0),
)


class PsiNetwork(nn.Module):
    """Log-scale of ψ per step and axis from the normalised innovations around the step.

    Per axis it sees ``log(1 + |ẽ|)`` of its own innovation and the root-mean-square over the
    axes, over ``2·half_window + 1`` steps centred on the step (a smoother may look ahead: a
    maneuver's onset is clear only steps later). The same weights serve every axis, so it
    takes any number of axes. Its last layer starts at zero: ψ_t starts at the constant ψ.
    """

    def __init__(self, half_window: int = 3, hidden: int = 16) -> None:
        super().__init__()
        self.half_window = half_window
        self.hidden = nn.Conv1d(2, hidden, 2 * half_window + 1, padding=half_window)
        self.out = nn.Conv1d(hidden, 1, 1)
        nn.init.zeros_(self.out.weight)
        nn.init.zeros_(self.out.bias)
        #: log of a factor on every file's fitted q: with it lower, ψ_t decides where to inflate
        self.log_q = nn.Parameter(torch.zeros((), dtype=torch.float64))

    def forward(self, normalised: Tensor) -> Tensor:
        """``[B, T, m]`` normalised innovations (0 where missing) → ``[B, T, m]`` log-scales."""
        B, T, m = normalised.shape
        own = normalised.abs().log1p()
        common = normalised.square().mean(-1, keepdim=True).sqrt().log1p().expand(B, T, m)
        features = torch.stack([own, common], dim=-1)  # [B, T, m, 2]
        features = features.permute(0, 2, 3, 1).reshape(B * m, 2, T)
        log_scale = self.out(torch.tanh(self.hidden(features)))  # [B·m, 1, T]
        return log_scale.reshape(B, m, T).mT


class ScaledQ(nn.Module):
    """A model's ``q``: the settings' value times the network's shared factor ``exp(log_q)``."""

    def __init__(self, q: float, log_q: nn.Parameter) -> None:
        super().__init__()
        self.register_buffer("base", torch.tensor(q, dtype=torch.float64))
        self.log_q = log_q

    def forward(self) -> Tensor:
        return self.base * self.log_q.exp()


class NetworkPsiSVSS(nn.Module):
    """An SVSS over the variable boundary layer of ``settings`` whose limit ψ is scaled per step
    by a network of a Kalman filter pre-pass's normalised innovations, and whose ``q`` is the
    settings' times the network's shared factor (the pre-pass runs on the settings' own q)."""

    def __init__(self, settings: Settings, network: PsiNetwork) -> None:
        super().__init__()
        model = make_model(settings)
        assert settings.q is not None
        self.pre = KalmanFilter(make_model(settings))
        model.q = ScaledQ(settings.q, network.log_q)
        svss = make_estimator(settings, model)
        assert isinstance(svss, SVSS)
        self.svss = svss
        self.network = network

    @property
    def model(self) -> Any:
        return self.svss.model

    def psi(self, z: Tensor, x0: Tensor, P0: Tensor, dt: Tensor | None = None) -> Tensor:
        """The per-step limits ``[B, T, m]``."""
        with torch.no_grad():
            kf = self.pre(z, x0, P0, dt=dt)
        std = kf.innovation_cov.diagonal(dim1=-2, dim2=-1).clamp_min(1e-12).sqrt()
        normalised = (kf.innovation / std).nan_to_num(0.0) * ~torch.isnan(z)
        base = self.svss.filter.psi.detach().to(z.dtype)
        return base * self.network(normalised.to(torch.float32)).to(z.dtype).exp()

    def forward(self, z: Tensor, x0: Tensor, P0: Tensor, **kwargs: Any) -> Any:
        return self.svss(z, x0, P0, psi=self.psi(z, x0, P0, kwargs.get("dt")), **kwargs)


@dataclass
class Half:
    """One half of a set: its tracks, their truth, and estimators on its own fitted settings."""

    name: str
    tracks: RecordedTracks  #: centred, with priors
    truth: Tensor  #: [B, T, m] true positions, centred alike
    ks: nn.Module
    svss: SVSS
    settings: Settings  #: the SVSS's
    meas_var: Tensor  #: [m] read off the data


def read_set(kind: str, sigma: float, rows: int, seed: int, folder: Path) -> tuple[Any, Any]:
    """A benchmark set's measured tracks and its truth, read as ``torchsvs track`` reads them."""
    (bench,) = build_sets([kind], rows=rows, seed=seed, sigmas=[sigma])
    source, truth_path = bench.write(folder)
    tracks, _ = read_tracks(source)
    truth, _ = read_tracks(truth_path, meas_std=1.0)
    if tracks.ids != truth.ids or not torch.equal(torch.isnan(tracks.z), torch.isnan(truth.z)):
        raise RuntimeError(f"{bench.name}: the truth's rows do not match the measurements'")
    return bench.name, (tracks, truth.z)


def fitted(estimator: str, tracks: RecordedTracks) -> Settings:
    """The truth-free settings of ``estimator`` on ``tracks``: read off them and fitted as
    ``torchsvs track --fit`` does (without its outlier screen and per-track q)."""
    settings = complete_settings(Settings(estimator=estimator), tracks)
    return self_tune(settings, tracks).settings


def make_half(name: str, tracks: RecordedTracks, truth: Tensor) -> Half:
    """A half with the settings ``--fit`` reaches on it (KS and SVSS)."""
    return half_of(name, tracks, truth, fitted("svss", tracks), fitted("ks", tracks))


def half_of(
    name: str, tracks: RecordedTracks, truth: Tensor, settings: Settings, ks_settings: Settings
) -> Half:
    """A half on the SVSS's ``settings`` (and the KS's): the tracks moved to start near 0,
    with the priors of the moved measurements, and their truth ``[B, T, m]`` moved alike."""
    assert settings.meas_var is not None
    moved, offset = centred(tracks)
    meas_var = torch.tensor(settings.meas_var, dtype=torch.float64)
    svss = make_estimator(settings, make_model(settings))
    assert isinstance(svss, SVSS)
    return Half(
        name,
        with_prior(moved, meas_var.sqrt()),
        truth[:, : tracks.z.shape[1]] - offset.unsqueeze(1),
        make_estimator(ks_settings, make_model(ks_settings)),
        svss,
        settings,
        meas_var,
    )


def halves(tracks: RecordedTracks, seed: int) -> tuple[Tensor, Tensor]:
    """The track indices of two halves, drawn at random (seeded)."""
    order = torch.randperm(len(tracks), generator=torch.Generator().manual_seed(seed))
    return order[0::2].sort().values, order[1::2].sort().values


def position_rmse(mean: Tensor, truth: Tensor) -> float:
    """2-D position RMSE (m): the root of the mean squared distance over observed steps."""
    error = (mean[..., 0::2] - truth).square().sum(-1)
    seen = ~torch.isnan(truth).any(-1)
    return float(error[seen].mean().sqrt())


def train(
    network: PsiNetwork, training: list[Half], epochs: int, lr: float, seed: int
) -> list[float]:
    """Fits the network (and its ``q`` factor) by SURE on every window of ``training``, each
    half through its own settings: one Adam step per epoch on the whole set, with the same
    probes every epoch (common random numbers: the loss is one function of the weights, so the
    descent does not chase the probes' noise). The loss per epoch."""
    jobs = []
    for half in training:
        module = NetworkPsiSVSS(half.settings, network)
        (batch,) = recorded_batches(half.tracks, half.meas_var, WINDOW, BURN_IN, None)
        jobs.append((module, batch, torch.diag(half.meas_var)))
    optimiser = torch.optim.Adam(network.parameters(), lr=lr)
    losses = []
    for _ in tqdm(range(epochs), desc="epochs", leave=False):
        optimiser.zero_grad()
        total = 0.0
        for module, batch, R in jobs:
            probes = torch.Generator().manual_seed(seed)
            loss, _ = batch_loss(module, batch, "sure", meas_cov=R, generator=probes, keep="mean")
            (loss / len(jobs)).backward()
            total += float(loss.detach()) / len(jobs)
        optimiser.step()
        losses.append(total)
    return losses


def held_out(half: Half, network: PsiNetwork | None, seed: int) -> tuple[float, float]:
    """The half's SVSS (with the network's ψ_t if given): its true 2-D position RMSE (m) and
    the truth-free estimate of it that ``torchsvs track`` prints (:mod:`torchsvs.accuracy`), from
    one run and one probed run."""
    estimator = half.svss if network is None else NetworkPsiSVSS(half.settings, network)
    std = half.meas_var.sqrt()

    def run(z: Tensor) -> Any:
        return run_result(estimator, with_prior(replace(half.tracks, z=z), std), keep="mean")

    out = run(half.tracks.z)
    mean = out.mean
    probe = draw_probe(half.tracks.z, std, PROBE_STEP, torch.Generator().manual_seed(seed))
    control = reference_for(estimator, out, with_prior(half.tracks, std), std, probe)
    terms = risk_terms(
        lambda z: run(z).mean[..., 0::2],
        half.tracks.z,
        mean[..., 0::2],
        std,
        None,
        reference=None if control is None else control.reference(out),
        probe=probe,
    )
    estimate = accuracy_of(terms, half.meas_var.tolist()).estimated_rmse
    return position_rmse(mean, half.truth), estimate


#: Windows the network is trained on (steps, and steps of burn-in the loss does not count).
WINDOW, BURN_IN = 64, 16
#: What each network is trained on: the first halves of these kinds (None: every set).
TRAINING = {
    "every kind": None,
    "airliners": ("own", "scan10", "scan1"),
    "taxiing": ("taxi",),
    "simulated turns": ("turning",),
}


def figure(path: Path, ratios: dict[str, dict[str, float]]) -> None:
    """Held-out RMSE with the network's ψ_t over the SVSS's constant ψ, per set and network."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    sets = list(next(iter(ratios.values())))
    fig, ax = plt.subplots(figsize=(9, 4))
    width = 0.8 / len(ratios)
    for i, (label, per_set) in enumerate(ratios.items()):
        x = [j + (i - (len(ratios) - 1) / 2) * width for j in range(len(sets))]
        ax.bar(x, [per_set[s] - 1 for s in sets], width, bottom=1, label=f"trained on {label}")
    ax.axhline(1, color="0.3", lw=0.8)
    ax.set_xticks(range(len(sets)), sets, rotation=20)
    ax.set(ylabel="RMSE / SVSS --fit", title="ψ_t from a network, on held-out halves")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--epochs", type=int, default=40)
    parser.add_argument("--rows", type=int, default=5000, help="rows per set (about)")
    parser.add_argument("--lr", type=float, default=0.01)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "results")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)  # small tensors in a step loop: one thread is fastest
    start = time.perf_counter()
    first: dict[str, Half] = {}
    second: dict[str, Half] = {}
    with tempfile.TemporaryDirectory() as folder:
        for kind, sigma in tqdm(SETS, desc="sets and their fits"):
            name, (tracks, truth) = read_set(kind, sigma, args.rows, args.seed, Path(folder))
            a, b = halves(tracks, args.seed)
            first[name] = make_half(name, tracks.subset(a), truth[a])
            second[name] = make_half(name, tracks.subset(b), truth[b])
    networks: dict[str, PsiNetwork] = {}
    notes = []
    for label, kinds in TRAINING.items():
        chosen = [h for n, h in first.items() if kinds is None or n.split(" ")[0] in kinds]
        torch.manual_seed(args.seed)
        network = PsiNetwork()
        t0 = time.perf_counter()
        losses = train(network, chosen, args.epochs, args.lr, args.seed)
        networks[label] = network
        notes.append(
            f"trained on {label} ({len(chosen)} {'half' if len(chosen) == 1 else 'halves'}): "
            f"SURE {losses[0]:.4f} → "
            f"{losses[-1]:.4f}, q × {float(network.log_q.detach().exp()):.2f}, "
            f"{time.perf_counter() - t0:.0f} s"
        )
        print(notes[-1], flush=True)
    rows, ratios = [], {label: {} for label in networks}
    estimate_rows = []
    for name, half in second.items():
        ks = position_rmse(run_result(half.ks, half.tracks, keep="mean").mean, half.truth)
        svss, guess = held_out(half, None, args.seed)
        cells = [name, len(half.tracks), f"{ks:.1f}", f"{svss:.1f} ({svss / ks:.3f})"]
        estimates = [name, f"{guess:.1f} / {svss:.1f}"]
        for label, network in networks.items():
            value, guess = held_out(half, network, args.seed)
            ratios[label][name] = value / svss
            cells.append(f"{value / svss:.3f}")
            estimates.append(f"{guess:.1f} / {value:.1f}")
        rows.append(cells)
        estimate_rows.append(estimates)
    mean = ["mean", "", "", ""] + [f"{sum(r.values()) / len(r):.3f}" for r in ratios.values()]
    rows.append(mean)
    header = ["held-out half", "tracks", "KS --fit m", "SVSS --fit m (× KS)"] + [
        f"ψ_t, trained on {label} (× SVSS)" for label in networks
    ]
    table = markdown_table(header, rows)
    estimate_table = markdown_table(
        ["held-out half", "SVSS --fit"] + [f"trained on {label}" for label in networks],
        estimate_rows,
    )
    args.out.mkdir(parents=True, exist_ok=True)
    figure(args.out / "network_psi.png", ratios)
    elapsed = time.perf_counter() - start
    text = render(
        "network_psi",
        "report",
        command=f"python -m experiments.network_psi --epochs {args.epochs} --rows {args.rows} "
        f"--lr {args.lr} --seed {args.seed}",
        notes="\n".join(f"- {n}" for n in notes),
        table=table,
        estimates=estimate_table,
        elapsed=f"{elapsed / 60:.1f}",
        weights=sum(p.numel() for p in PsiNetwork().parameters()),
    )
    (args.out / "network_psi.md").write_text(text)
    print(table)
    print(f"total {elapsed:.0f} s")


if __name__ == "__main__":
    main()

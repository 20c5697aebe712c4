"""A PyTorch MLP (ReLU hidden layers, a linear output): Adam on the mean squared error, mini-batches, the
best validation epoch's weights kept, seeded and reproducible. Imported through
:func:`quadcore.learn.backends.backend`."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch

from quadcore.learn.learners import LearningError

if TYPE_CHECKING:
    from quadcore.learn.learners import LearnerSpec
    from quadcore.learn.splits import TrainingData

FILE = "model.pt"


def module(n_in: int, hidden: tuple[int, ...], n_out: int) -> torch.nn.Sequential:
    layers: list[torch.nn.Module] = []
    width = n_in
    for h in hidden:
        layers += [torch.nn.Linear(width, h), torch.nn.ReLU()]
        width = h
    layers.append(torch.nn.Linear(width, n_out))
    return torch.nn.Sequential(*layers)


def linear_layers(impl: torch.nn.Module) -> list[torch.nn.Linear]:
    """The network's linear layers in order (a ReLU follows each but the last)."""
    return [m for m in impl if isinstance(m, torch.nn.Linear)]  # type: ignore[attr-defined]


def train(spec: LearnerSpec, d: TrainingData, seed: int, threads: int) -> tuple[torch.nn.Module, dict]:
    torch.set_num_threads(threads)
    torch.manual_seed(seed)
    gen = torch.Generator().manual_seed(seed)
    net = module(d.X_fit.shape[1], spec.hidden, d.Y_fit.shape[1])
    opt = torch.optim.Adam(net.parameters(), lr=spec.lr, weight_decay=spec.weight_decay)
    xf, yf = torch.from_numpy(d.X_fit), torch.from_numpy(d.Y_fit.astype(np.float32))
    xv, yv = torch.from_numpy(d.X_val), torch.from_numpy(d.Y_val.astype(np.float32))
    n, bs = len(xf), max(1, spec.batch_size)
    best, best_state, best_epoch, bad, epochs = float("inf"), None, -1, 0, 0
    for epoch in range(spec.max_epochs):
        net.train()
        perm = torch.randperm(n, generator=gen)
        for i in range(0, n, bs):
            idx = perm[i: i + bs]
            loss = torch.nn.functional.mse_loss(net(xf[idx]), yf[idx])
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
        net.eval()
        with torch.no_grad():
            vl = float(torch.nn.functional.mse_loss(net(xv), yv))
        epochs = epoch + 1
        if vl < best:
            best, best_epoch, bad = vl, epoch, 0
            best_state = {k: v.detach().clone() for k, v in net.state_dict().items()}
        else:
            bad += 1
            if bad >= spec.patience:
                break
    if best_state is None:  # no epoch ran, or every validation loss was NaN (diverged)
        raise LearningError(f"MLP {spec.label}: no epoch gave a finite validation loss "
                            f"({epochs} epoch(s) run): raise max_epochs or lower lr")
    net.load_state_dict(best_state)
    net.eval()
    return net, {"epochs": epochs, "best_epoch": best_epoch, "val_loss": best}


def predict(impl: torch.nn.Module, Z: np.ndarray) -> np.ndarray:
    """Scaled features (n, k) float32 -> scaled outputs (n, 6)."""
    with torch.no_grad():
        return impl(torch.from_numpy(Z)).numpy()


def save(impl: torch.nn.Module, folder: Path) -> None:
    torch.save(impl.state_dict(), folder / FILE)


def load(folder: Path, spec: LearnerSpec, n_in: int, n_out: int, threads: int) -> torch.nn.Module:
    torch.set_num_threads(threads)
    impl = module(n_in, spec.hidden, n_out)
    impl.load_state_dict(torch.load(folder / FILE, weights_only=True))
    impl.eval()
    return impl

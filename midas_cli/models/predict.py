"""A trained gesture network's predictions: class log-probabilities and classes per frame, in eval mode."""

from __future__ import annotations

import numpy as np
import torch

from midas_cli.models.sequences import Sequences


def predict(model: torch.nn.Module, seqs: Sequences, device: torch.device) -> list[np.ndarray]:
    """Class index per frame (T_i,) for every unit, in eval mode."""
    return [lp.argmax(axis=0) for lp in predict_log_probs(model, seqs, device)]


def predict_log_probs(model: torch.nn.Module, seqs: Sequences, device: torch.device) -> list[np.ndarray]:
    """Log-probabilities of the classes (C, T_i) for every unit, in eval mode."""
    model.eval()
    out = []
    with torch.no_grad():
        for x in seqs.x:
            inputs = torch.from_numpy(x.T[None]).to(device)  # (T, D) -> (1, D, T)
            mask = torch.ones(1, x.shape[0], dtype=torch.bool, device=device)
            logits = model.frame_logits(model(inputs, mask))[0].float()
            out.append(torch.log_softmax(logits, dim=0).cpu().numpy())
    return out


def frame_accuracy(model: torch.nn.Module, seqs: Sequences, device: torch.device) -> float:
    preds = predict(model, seqs, device)
    truth = np.concatenate(seqs.y)
    keep = truth >= 0
    return float((np.concatenate(preds)[keep] == truth[keep]).mean()) if keep.any() else 0.0

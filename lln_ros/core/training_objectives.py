"""The two training objectives of the LLN head (training.py's module doc says what they are):
the rerank objective's soft top-n membership, its soft score S~ over fixed mutual-match tables, and
its listwise loss; the paper's triplet loss on the LLN-weighted embedding."""

from __future__ import annotations

import numpy as np
import torch

from .similarity import cross_match, offset_mode, offset_weights


def soft_selection(logits: torch.Tensor, n: int, temp: float) -> torch.Tensor:
    """logits (B, N) -> (B, N) soft top-n membership in (0, 1): 1/2 at the n-th largest logit."""
    kth = torch.topk(logits, min(n, logits.shape[1]), dim=1).values[:, -1:].detach()
    return torch.sigmoid((logits - kth) / temp)


def soft_similarity(
    a_q: torch.Tensor, a_c: torch.Tensor, partner: torch.Tensor, value: torch.Tensor, n: int
) -> torch.Tensor:
    """S~ of B queries against C candidates each.

    a_q (B, N), a_c (B, C, N) soft memberships; partner (B, C, N) long: the mutual partner of query
    cell i in candidate c (any index where there is none); value (B, C, N): w_ij * s_ij (0 where none).
    Returns (B, C)."""
    return (a_q[:, None] * torch.gather(a_c, 2, partner) * value).sum(2) / n


def match_tables(
    fq: np.ndarray,
    fc: np.ndarray,
    cells: np.ndarray,
    scale: float = 1.0,
    valid_q: np.ndarray | None = None,
    valid_c: np.ndarray | None = None,
):
    """Mutual matches of every cell of one query against C candidates, with their offset weights.

    fq (N, D), fc (C, N, D) L2-normalised; cells (N, 2) (col, row); valid_q (N,), valid_c (C, N)
    bool: real (not padded) cells, default all. Returns partner (C, N) int (0 where query cell i
    has no mutual partner) and value (C, N) float32 = w_ij * s_ij (0 there)."""
    n = len(fq)
    valid_q = np.ones(n, bool) if valid_q is None else valid_q
    valid_c = np.ones(fc.shape[:2], bool) if valid_c is None else valid_c
    match, sims = cross_match(fq, fc, valid_q, valid_c)
    matched = match >= 0
    offsets = cells[None] - cells[np.maximum(match, 0)]
    weight = np.where(matched, offset_weights(offsets, offset_mode(offsets, matched, sims), scale), 0.0)
    return np.maximum(match, 0), (weight * sims).astype(np.float32)


def rerank_loss(scores: torch.Tensor, n_pos: torch.Tensor, valid: torch.Tensor, tau: float) -> torch.Tensor:
    """scores (B, C) S~ with the positives first (n_pos (B,) of them); valid (B, C) bool.
    Mean over queries of -log(softmax mass of the positives)."""
    s = scores.masked_fill(~valid, -1e4) / tau
    pos = (torch.arange(s.shape[1])[None] < n_pos[:, None]) & valid
    return (torch.logsumexp(s, 1) - torch.logsumexp(s.masked_fill(~pos, -1e4), 1)).mean()


def triplet_loss(fq: torch.Tensor, fp: torch.Tensor, fn: torch.Tensor, margin: float) -> torch.Tensor:
    """fq, fp (B, D); fn (B, K, D). Sum over negatives of the hinge, mean over tuples."""
    d_pos = (fq - fp).norm(dim=1)  # (B,)
    d_neg = (fq[:, None] - fn).norm(dim=2)  # (B, K)
    return torch.relu(d_pos[:, None] + margin - d_neg).sum(1).mean()

"""The Landmark Localization Network head (Xin et al., ICRA 2019, Sec. III-A) and its checkpoints.

    features (B, D, h, w)  ->  parallel convs (k x k, one per kernel size, `channels` each)
                           ->  concat (B, K*channels, h, w) -> ReLU -> 1x1 conv  = c (B, h, w)
    norm_prior p > 0:       logits = p log|f| + c   (c -> b tanh(c / b) with correction_bound b > 0)
                           ->  ReLU -> activation (B, h, w), non-negative

A checkpoint is one torch file holding the head's state dict and the metadata that says which
descriptor space it belongs to (backbone, layer, descriptor size), so a head, or a map built with it,
is never silently combined with features from another model.
"""

from __future__ import annotations

import hashlib
import os

import torch
from torch import nn

from ..errors import ModelError
from .backbones import load_strict

CHECKPOINT_VERSION = 1

default_conf = {
    'kernel_sizes': (1, 3, 5),  # multi-scale: robustness to viewpoint change and occlusion
    'channels': 64,  # per branch
    'seed': 0,  # Xavier init is seeded so an untrained head is the same everywhere
    # weight of log |f_ij| (the feature norm ACT ranks by) added to the logits. > 0 also starts the
    # 1x1 fuse at zero, so the untrained head ranks exactly as ACT and training learns a correction
    # to ACT's choice instead of a selection from scratch (see docs/generalisation.md)
    'norm_prior': 0.0,
    # with norm_prior > 0: the learned correction c is squashed to bound * tanh(c / bound), so the head
    # moves a cell's log-norm by at most +-bound. 0 = unbounded (heads trained before 2026-12-06):
    # trained on a ranking-only loss, c grew to 1e4 times log|f|'s spread and the prior was switched
    # off in practice, leaving a fixed centre prior that loses off-domain (docs/generalisation.md)
    'correction_bound': 0.0,
    # how the k > 1 branches pad the feature map: 'zeros' (heads trained before 2026-12-06) gives the
    # border cells a signal of their own, from which the head learned where Nordland's discriminative
    # cells usually are; 'replicate' gives the border no content the image does not have
    'padding': 'zeros',
}
PADDINGS = ('zeros', 'replicate')


class LLNHead(nn.Module):
    def __init__(self, in_dim: int, conf: dict | None = None):
        super().__init__()
        self.conf = conf = {**default_conf, **(conf or {})}
        self.in_dim = int(in_dim)
        if conf['padding'] not in PADDINGS:
            raise ModelError(f'LLN head padding must be one of {PADDINGS}, got {conf["padding"]!r}')
        if float(conf['correction_bound']) < 0:
            raise ModelError(f'LLN head correction_bound must be >= 0, got {conf["correction_bound"]}')
        self.branches = nn.ModuleList(
            nn.Conv2d(in_dim, conf['channels'], k, padding=k // 2, padding_mode=conf['padding'])
            for k in conf['kernel_sizes']
        )
        self.fuse = nn.Conv2d(conf['channels'] * len(conf['kernel_sizes']), 1, 1)
        generator = torch.Generator().manual_seed(int(conf['seed']))
        for conv in [*self.branches, self.fuse]:
            # Xavier-uniform drawn from our own generator: reproducible without touching global RNG
            fan_in = conv.in_channels * conv.kernel_size[0] * conv.kernel_size[1]
            fan_out = conv.out_channels * conv.kernel_size[0] * conv.kernel_size[1]
            bound = (6.0 / (fan_in + fan_out)) ** 0.5
            with torch.no_grad():
                conv.weight.copy_(torch.rand(conv.weight.shape, generator=generator) * 2 * bound - bound)
                conv.bias.zero_()
        if conf['norm_prior']:
            with torch.no_grad():
                self.fuse.weight.zero_()

    def logits(self, features: torch.Tensor) -> torch.Tensor:
        """features (B, D, h, w) -> the 1x1 fuse output before its ReLU (B, h, w)."""
        # a nonlinearity between the branches and the 1x1 fuse; without it the parallel convs and
        # the fuse collapse into one linear 5x5 conv and the multi-scale design buys nothing
        x = torch.relu(torch.cat([b(features) for b in self.branches], dim=1))
        out = self.fuse(x)[:, 0]
        if self.conf['norm_prior']:
            bound = float(self.conf['correction_bound'])
            if bound:
                out = bound * torch.tanh(out / bound)
            out = out + float(self.conf['norm_prior']) * torch.log(features.norm(dim=1) + 1e-6)
        return out

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        """features (B, D, h, w) -> activation w (B, h, w) >= 0 (the paper's ReLU output)."""
        return torch.relu(self.logits(features))


def embed(head: LLNHead, feats: torch.Tensor) -> torch.Tensor:
    """The paper's holistic embedding, what its triplet loss trains: feats (B, D, h, w) -> F (B, D),
    the LLN-weighted sum of the L2-normalised local features, L2-normalised."""
    w = head(feats)  # (B, h, w)
    f = torch.nn.functional.normalize(feats, dim=1)
    return torch.nn.functional.normalize((f * w[:, None]).sum((2, 3)) + 1e-8, dim=1)


def state_fingerprint(module: nn.Module) -> str:
    """Short content hash of a module's state (parameter and buffer names and values)."""
    h = hashlib.sha256()
    for name, t in sorted(module.state_dict().items()):
        h.update(name.encode())
        h.update(t.detach().cpu().numpy().tobytes())
    return h.hexdigest()[:12]


def head_fingerprint(head: LLNHead) -> str:
    """Short content hash of the head's parameters: names the selection model in map metadata."""
    return state_fingerprint(head)


def save_checkpoint(path: str, head: LLNHead, backbone: str, layer: str, **extra) -> None:
    """Write the head and its metadata. `extra` (e.g. training command, data split) is kept as is."""
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    meta = {
        'version': CHECKPOINT_VERSION,
        'backbone': backbone,
        'layer': layer,
        'descriptor_dim': head.in_dim,
        'head_conf': {k: (list(v) if isinstance(v, tuple) else v) for k, v in head.conf.items()},
        **extra,
    }
    tmp = path + '.tmp'
    torch.save({'meta': meta, 'state_dict': head.state_dict()}, tmp)
    os.replace(tmp, path)  # never leave a half-written checkpoint under the real name


def load_checkpoint(
    path: str, backbone: str | None = None, layer: str | None = None, descriptor_dim: int | None = None
) -> tuple[LLNHead, dict]:
    """Load a head; when backbone / layer / descriptor_dim are given they must match its metadata."""
    if not os.path.isfile(path):
        raise ModelError(f'LLN checkpoint not found: {path!r}')
    try:
        blob = torch.load(path, map_location='cpu', weights_only=True)
        meta, state = blob['meta'], blob['state_dict']
    except Exception as e:
        raise ModelError(f'{path!r} is not an lln_ros checkpoint: {e}') from e
    if meta.get('version') != CHECKPOINT_VERSION:
        raise ModelError(
            f'{path!r}: checkpoint version {meta.get("version")} is not supported '
            f'(this lln_ros reads version {CHECKPOINT_VERSION})'
        )
    for key, want in (('backbone', backbone), ('layer', layer), ('descriptor_dim', descriptor_dim)):
        if want is not None and meta.get(key) != want:
            raise ModelError(
                f'{path!r} was trained for {key}={meta.get(key)!r}, but the model is configured with {key}={want!r}'
            )
    conf = dict(meta['head_conf'])
    conf['kernel_sizes'] = tuple(conf['kernel_sizes'])
    head = LLNHead(meta['descriptor_dim'], conf)
    load_strict(head, state, f'{path!r}: weights do not fit the head shape in its metadata')
    return head.eval(), meta

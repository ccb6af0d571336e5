"""Image -> LandmarkSet: frozen backbone + LLN head + landmark selection.

    extractor = Extractor({'top_n': 50, 'method': 'lln'})
    landmarks = extractor(image)            # uint8 (H, W) or (H, W, 3|4), RGB unless channel_order='bgr'
    many = extractor.extract_batch(images)  # same result, batched through the network

`runtime` picks what runs the network (lln_ros.core.runtime): 'onnxruntime' (the default; the graph is
exported once and cached, see lln_ros.core.runtime) or 'torch'. Both give the same landmarks; when ONNX
Runtime is not installed the extractor says so in one log line and runs torch. model_info['runtime']
names the one that runs.
"""

from __future__ import annotations

import os
from importlib import resources

import numpy as np
import torch

from ..errors import ModelError
from ..io.image import check_image, resize_for_network
from . import backbones
from .landmarks import METHODS, LandmarkSet, l2_normalize, select_landmarks
from .lln import LLNHead, head_fingerprint, load_checkpoint
from .runtime import RUNTIMES, build_network

default_conf = {
    'backbone': backbones.default_conf,
    'weights': '',  # LLN head checkpoint; '' = the one shipped for this backbone/layer
    'top_n': 50,
    'input_height': 288,
    'method': 'lln',
    'rand_seed': 0,
    # lln only: rank cells by (1 - a) rank(head logits) + a rank(|f|) (rank fusion with ACT's feature
    # norm, per image), a in [0, 1]: 0 = the head alone, 1 = ACT. Pulls the selection toward the
    # untrained choice where the head meets kinds of place it never trained on
    # (docs/generalisation.md, "Unseen kinds of place")
    'act_fusion': 0.0,
    'runtime': 'onnxruntime',  # torch | onnxruntime (falls back to torch when not installed) | onnxruntime-int8
    'num_threads': 0,  # intra-op threads of the runtime; 0 = the runtime's default
}


def shipped_weights(backbone: str, layer: str) -> str | None:
    """Path of the head checkpoint shipped in the package for this backbone/layer, if any."""
    path = resources.files('lln_ros') / 'weights' / f'lln_{backbone}_{layer}.pt'
    return str(path) if path.is_file() else None


def _unit_ranks(x: np.ndarray) -> np.ndarray:
    """Ranks of x's cells scaled to [0, 1] (0 = lowest); equal values: the lower index ranks lower."""
    flat = x.ravel()
    r = np.empty(flat.size, np.float32)
    r[np.argsort(flat, kind='stable')] = np.arange(flat.size, dtype=np.float32) / max(flat.size - 1, 1)
    return r.reshape(x.shape)


def fused_logits(logits: np.ndarray, norms: np.ndarray, a: float) -> np.ndarray:
    """(rows, cols) head logits and feature norms -> the map lln ranks by: the head's logits at a = 0,
    else the rank fusion (1 - a) rank(logits) + a rank(|f|) (ranks scaled to [0, 1] per image).

    Ranks, not values: a trained head's logits are thousands (the shipped head's span 2,000-25,000
    on one image) against log |f| of 3.7-4.7, so a convex mix of values is the head alone for any
    a < 0.999; ranks put the two on one scale whatever the head's."""
    if not a:
        return logits
    return (1.0 - a) * _unit_ranks(logits) + a * _unit_ranks(norms)


class Extractor:
    def __init__(self, conf: dict | None = None):
        conf = dict(conf or {})
        conf['backbone'] = {**backbones.default_conf, **(conf.get('backbone') or {})}
        self.conf = conf = {**default_conf, **conf}
        if conf['method'] not in METHODS:
            raise ModelError(f'unknown method {conf["method"]!r}; choose one of {METHODS}')
        if int(conf['top_n']) < 1:
            raise ModelError(f'top_n must be at least 1, got {conf["top_n"]}')
        if not 0.0 <= float(conf['act_fusion']) <= 1.0:
            raise ModelError(f'act_fusion must be in [0, 1], got {conf["act_fusion"]}')
        if conf['runtime'] not in RUNTIMES:
            raise ModelError(f'unknown runtime {conf["runtime"]!r}; choose one of {list(RUNTIMES)}')
        if int(conf['num_threads']):
            torch.set_num_threads(int(conf['num_threads']))  # also the torch head of from_features
        self.backbone = backbones.build_backbone(conf['backbone'])
        name, layer = conf['backbone']['name'], self.backbone.layer
        weights = conf['weights'] or shipped_weights(name, layer)
        if weights:
            self.head, self.head_meta = load_checkpoint(os.path.expanduser(weights), name, layer, self.backbone.dim)
        else:
            # no trained head for this backbone/layer: a seeded Xavier head, and the metadata says so
            self.head = LLNHead(self.backbone.dim).eval()
            self.head_meta = {'trained': False}
        for p in self.head.parameters():
            p.requires_grad_(False)
        self.network = build_network(name, layer, self.backbone, self.head, conf['runtime'], int(conf['num_threads']))
        self.descriptor_space = f'{name}/{layer}/{self.backbone.dim}'
        self.model_info = {
            'backbone': name,
            'layer': layer,
            'descriptor_dim': self.backbone.dim,
            'descriptor_space': self.descriptor_space,
            'head': head_fingerprint(self.head),
            'head_trained': bool(self.head_meta.get('trained', True)),
            'weights': weights or '',
            'input_height': int(conf['input_height']),
            # not part of the descriptor space: maps built with one runtime answer the other's queries
            'runtime': self.network.runtime,
        }

    def backbone_features(self, rgb_batch: np.ndarray) -> torch.Tensor:
        """RGB uint8 (B, H, W, 3), already at network size -> features (B, D, H/32, W/32).

        Rounded to float16 precision: the feature cache stores float16, so live extraction and
        evaluation from the cache see the same numbers (and agree on every ranking)."""
        return torch.from_numpy(self.network(rgb_batch)[0])

    def features(self, rgb_batch: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """RGB uint8 (B, H, W, 3) at network size -> (features (B, D, h, w), head logits (B, h, w)),
        float32 numpy arrays, the features float16-exact."""
        return self.network(rgb_batch)

    def __call__(self, image: np.ndarray, channel_order: str = 'rgb') -> LandmarkSet:
        return self.extract_batch([image], channel_order)[0]

    def extract_batch(self, images: list, channel_order: str = 'rgb', batch_size: int = 8) -> list[LandmarkSet]:
        """Extract many images; images of the same network size go through the network together."""
        rgb = [check_image(im, channel_order) for im in images]
        net = [resize_for_network(im, int(self.conf['input_height'])) for im in rgb]
        out: list[LandmarkSet | None] = [None] * len(rgb)
        by_size: dict[tuple, list[int]] = {}
        for i, im in enumerate(net):
            by_size.setdefault(im.shape, []).append(i)
        for idx in by_size.values():
            for start in range(0, len(idx), batch_size):
                chunk = idx[start : start + batch_size]
                feats, logits = self.features(np.stack([net[i] for i in chunk]))
                for j, i in enumerate(chunk):
                    h, w = rgb[i].shape[:2]
                    out[i] = self._landmarks(feats[j], logits[j], (w, h))
        return out

    @torch.inference_mode()
    def from_features(self, feats: np.ndarray, image_size: tuple) -> LandmarkSet:
        """LandmarkSet from a cached backbone feature map (D, rows, cols) of an image whose original
        size is image_size = (width, height): the head and the selection run, the backbone does not."""
        f = torch.from_numpy(np.asarray(feats, np.float32))[None]
        return self._landmarks(f[0].numpy(), self.head.logits(f)[0].numpy(), image_size)

    def _landmarks(self, feats: np.ndarray, logits: np.ndarray, image_size: tuple) -> LandmarkSet:
        """feats (D, rows, cols), head logits (rows, cols) -> LandmarkSet in original image pixels."""
        d, rows, cols = feats.shape
        local = feats.reshape(d, rows * cols).T  # (rows*cols, D)
        method = self.conf['method']
        activation = np.maximum(logits, 0)
        # LLN ranks by the logits: the same order as the ReLU activation where it is positive, and
        # a meaningful order among the many cells the ReLU sets to exactly 0 (by index they would
        # fall back to the top rows of the image: ceiling and sky)
        norms = np.linalg.norm(local, axis=1).reshape(rows, cols)
        rank_by = norms if method == 'act' else fused_logits(logits, norms, float(self.conf.get('act_fusion', 0.0)))
        cells_flat = select_landmarks(rank_by, int(self.conf['top_n']), method, int(self.conf['rand_seed']))
        cells = np.stack([cells_flat % cols, cells_flat // cols], axis=1).astype(np.int32)
        cell_size = np.array([image_size[0] / cols, image_size[1] / rows], np.float32)
        centers = ((cells + 0.5) * cell_size).astype(np.float32)
        return LandmarkSet(
            global_descriptor=l2_normalize(local.max(axis=0)).astype(np.float32),
            # float16-exact, as the map stores them: a map answers like the offline evaluation
            descriptors=l2_normalize(local[cells_flat]).astype(np.float16).astype(np.float32),
            cells=cells,
            centers=centers,
            # lln with act_fusion: the fused rank score the cells are ordered by, in [0, 1]
            scores=(rank_by if method == 'act' or rank_by is not logits else activation)
            .ravel()[cells_flat]
            .astype(np.float32),
            cell_size=cell_size,
            image_size=np.array(image_size, np.float32),
            grid=(rows, cols),
            activation=activation.astype(np.float32),
            descriptor_space=self.descriptor_space,
        )

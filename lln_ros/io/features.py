"""Backbone feature maps computed once and kept on disk.

The backbone is frozen, so training the LLN head and evaluating many methods only ever need its
output. A cache entry is keyed by the descriptor space (backbone/layer/D), the runtime's precision (int8
features are close to, not equal to, float ones: their own folder), the network input size rule and
the image file's content (sha1 of its bytes), so renaming files costs nothing and
changing any of them never returns stale features.

    cache = FeatureCache('cache/features', extractor)
    feats = cache.load(paths, size=(352, 352))   # list of float16 (D, h, w), squashed to 352x352
    feats = cache.load(paths, size=288)          # height 288, aspect kept (what extraction uses)
    sets = cache.landmark_sets(paths, 288)       # the extractor's LandmarkSets from those features
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from .image import load_image, resize_for_network


def file_digest(path: str | os.PathLike) -> str:
    h = hashlib.sha1()
    with open(path, 'rb') as f:
        for block in iter(lambda: f.read(1 << 20), b''):
            h.update(block)
    return h.hexdigest()


def resize_to(rgb: np.ndarray, size) -> np.ndarray:
    """size: an int (input height, aspect kept, as extraction does) or (width, height) (squash)."""
    if isinstance(size, int):
        return resize_for_network(rgb, size)
    w, h = (int(v) for v in size)
    interp = cv2.INTER_AREA if h < rgb.shape[0] else cv2.INTER_LINEAR
    return cv2.resize(rgb, (w, h), interpolation=interp)


class FeatureCache:
    def __init__(self, root: str | os.PathLike, extractor, batch_size: int = 8):
        self.extractor = extractor
        from ..core.runtime import QUANT_VERSION

        int8 = getattr(extractor.network, 'runtime', '') == 'onnxruntime-int8'
        self.root = Path(root) / (
            extractor.descriptor_space.replace('/', '_') + (f'_int8q{QUANT_VERSION}' if int8 else '')
        )
        self.batch_size = batch_size

    def _path(self, digest: str, size) -> Path:
        tag = f'h{size}' if isinstance(size, int) else f'{size[0]}x{size[1]}'
        return self.root / tag / digest[:2] / f'{digest}.npy'

    def load(self, paths: list, size=288, progress: str | None = None) -> list[np.ndarray]:
        """Feature maps float16 (D, h, w) for every image path, computing the missing ones."""
        digests = [file_digest(p) for p in paths]
        out: list = [None] * len(paths)
        missing = []
        for i, d in enumerate(digests):
            f = self._path(d, size)
            if f.is_file():
                try:
                    out[i] = np.load(f)
                    continue
                except (OSError, ValueError):
                    pass  # a torn write from an interrupted run: recompute it
            missing.append(i)
        bar = tqdm(total=len(missing), desc=progress or 'features', disable=progress is None or not missing, unit='img')
        for start in range(0, len(missing), self.batch_size):
            chunk = missing[start : start + self.batch_size]
            images = [resize_to(load_image(str(paths[i])), size) for i in chunk]
            by_shape: dict = {}
            for j, im in enumerate(images):
                by_shape.setdefault(im.shape, []).append(j)
            for group in by_shape.values():
                feats = self.extractor.backbone_features(np.stack([images[j] for j in group]))
                feats = feats.numpy().astype(np.float16)
                for j, f in zip(group, feats):
                    i = chunk[j]
                    out[i] = f
                    target = self._path(digests[i], size)
                    target.parent.mkdir(parents=True, exist_ok=True)
                    tmp = target.with_suffix(f'.{os.getpid()}.tmp')
                    with open(tmp, 'wb') as fh:
                        np.save(fh, f)
                    os.replace(tmp, target)
            bar.update(len(chunk))
        bar.close()
        return out

    def landmark_sets(self, paths: list, size: int = 288, progress: str | None = 'features') -> list:
        """The extractor's LandmarkSet of every image path, from its cached feature map (head and
        selection run; the backbone only for the missing ones), in original image pixels."""
        out = []
        for p, f in zip(paths, self.load(paths, size=size, progress=progress)):
            h, w = load_image(str(p)).shape[:2]
            out.append(self.extractor.from_features(f, (w, h)))
        return out

#!/usr/bin/env python3
"""Transformed copies of the shared sets that mimic the kinds of place where the shipped head lost
to untrained selection (issue 28): side views, seasonal webcams, small JPEG thumbnails.

    python scripts/shift_folds.py [--data ../shared/data] [--out out/shift]

Writes one VPR-Bench folder per fold (DIR/query/*, DIR/ref/*, DIR/ground_truth_new.npy), read by
`lln-eval --dataset vprbench:out/shift/FOLD`. The images are derived at run time from
../shared/data and live only in the git-ignored out/ (never committed). Places: the 210 essex3in1
references (outdoor / campus thumbnails, ~99x99) and the 84 rtabmap_loop frames (indoor, 512x384);
a query is correct for its own place and, on rtabmap, for every frame its ground truth says it
revisits (either direction). Every transform is seeded, so a second run writes the same bytes (the
feature cache keys on content).

Folds (query vs reference):
    lateral   left 70% of a frame vs its right 70% (40% of the frame in common; the lateral
              'left vs right side of the path' change, the rest of the scene unchanged)
    side      left 60% vs right 60%: the 20% in common is the query's right third and the
              reference's left third, i.e. it lies at the image border on both sides
    photo     a strong photometric change (dusk, over-exposure, colour cast, haze, one per image,
              seeded) vs the original (a static webcam at another time of day / weather)
    thumb     essex3in1's own query vs its reference (its real viewpoint/illumination change), both
              shrunk to 48 px height, the query JPEG q35 (small thumbnails with artefacts)
    webcam    photo's change on a 48 px thumbnail, JPEG q35, vs the 48 px thumbnail (photo + thumb)
"""

from __future__ import annotations

import argparse
import shutil
import sys
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from lln_ros.io.datasets import list_images  # noqa: E402

FOLDS = ('lateral', 'side', 'photo', 'thumb', 'webcam')
CROPS = {'lateral': 0.7, 'side': 0.6}  # crop width as a fraction of the frame
THUMB_H = 48  # thumbnail height in pixels
JPEG_Q = 35


def places(data: Path) -> tuple[list[Path], np.ndarray, list[Path]]:
    """(source images, (N, N) bool same-place matrix, essex queries aligned with the first 210)."""
    essex = list_images(data / 'essex3in1' / 'ref')
    essex_q = list_images(data / 'essex3in1' / 'query')
    gt_file = data / 'rtabmap_loop' / 'samples_GT.bmp'
    rt = [p for p in list_images(data / 'rtabmap_loop') if p.resolve() != gt_file.resolve()]
    g = cv2.imread(str(gt_file), cv2.IMREAD_GRAYSCALE) > 0
    n_e, n_r = len(essex), len(rt)
    same = np.eye(n_e + n_r, dtype=bool)
    same[n_e:, n_e:] |= g | g.T
    return essex + rt, same, essex_q


def photometric(bgr: np.ndarray, kind: int) -> np.ndarray:
    """One of four strong appearance changes of the whole image (uint8 BGR in and out)."""
    x = bgr.astype(np.float32) / 255
    if kind == 0:  # dusk: dark, low contrast, blue cast
        x = 0.45 * x**1.8 * np.array([1.25, 0.95, 0.75], np.float32)
    elif kind == 1:  # over-exposed, washed out (snow, glare)
        x = 1 - (1 - x) ** 2.2
        x = 0.6 * x + 0.4 * x.mean(axis=2, keepdims=True)
    elif kind == 2:  # warm evening light, saturated
        x = x**0.8 * np.array([0.7, 1.0, 1.3], np.float32)
    else:  # haze / fog: blend with grey-white, lowered contrast
        x = 0.55 * x + 0.45 * 0.85
    return np.clip(x * 255 + 0.5, 0, 255).astype(np.uint8)


def thumb(bgr: np.ndarray) -> np.ndarray:
    h, w = bgr.shape[:2]
    return cv2.resize(bgr, (max(1, round(w * THUMB_H / h)), THUMB_H), interpolation=cv2.INTER_AREA)


def jpeg(bgr: np.ndarray) -> np.ndarray:
    ok, buf = cv2.imencode('.jpg', bgr, [cv2.IMWRITE_JPEG_QUALITY, JPEG_Q])
    return cv2.imdecode(buf, cv2.IMREAD_COLOR)


def write_fold(out: Path, queries: list, refs: list, same: np.ndarray) -> None:
    for sub in ('query', 'ref'):
        (out / sub).mkdir(parents=True, exist_ok=True)
    for i, (q, r) in enumerate(zip(queries, refs)):
        cv2.imwrite(str(out / 'query' / f'{i:07d}.png'), q)
        if isinstance(r, Path):  # the original file, byte for byte: its cached features are reused
            shutil.copyfile(r, out / 'ref' / f'{i:07d}{r.suffix.lower()}')
        else:
            cv2.imwrite(str(out / 'ref' / f'{i:07d}.png'), r)
    rows = np.empty((len(queries), 2), object)
    for i in range(len(queries)):
        rows[i, 0], rows[i, 1] = i, [int(j) for j in np.flatnonzero(same[i])]
    np.save(out / 'ground_truth_new.npy', rows, allow_pickle=True)


def build(data: Path, out: Path, folds=FOLDS) -> dict:
    src, same, essex_q = places(data)
    images = [cv2.imread(str(p), cv2.IMREAD_COLOR) for p in src]
    kinds = np.random.default_rng(0).integers(0, 4, len(images))
    made = {}
    for fold in folds:
        if fold in CROPS:
            w = [im.shape[1] for im in images]
            q = [im[:, : round(CROPS[fold] * wi)] for im, wi in zip(images, w)]
            r = [im[:, wi - round(CROPS[fold] * wi) :] for im, wi in zip(images, w)]
            s = same
        elif fold == 'photo':
            q, r, s = [photometric(im, k) for im, k in zip(images, kinds)], src, same
        elif fold == 'thumb':
            n = len(essex_q)
            q = [jpeg(thumb(cv2.imread(str(p), cv2.IMREAD_COLOR))) for p in essex_q]
            r, s = [thumb(im) for im in images[:n]], same[:n, :n]
        elif fold == 'webcam':
            r = [thumb(im) for im in images]
            q, s = [jpeg(photometric(t, k)) for t, k in zip(r, kinds)], same
        else:
            raise SystemExit(f'unknown fold {fold!r}; choose from {FOLDS}')
        write_fold(out / fold, q, r, s)
        made[fold] = len(q)
    return made


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    p.add_argument('--data', default='../shared/data')
    p.add_argument('--out', default='out/shift')
    p.add_argument('--folds', default=','.join(FOLDS))
    a = p.parse_args()
    made = build(Path(a.data), Path(a.out), [f for f in a.folds.split(',') if f])
    for fold, n in made.items():
        print(f'{a.out}/{fold}: {n} queries, {n} references')
    return 0


if __name__ == '__main__':
    sys.exit(main())

"""Timing for lln-eval: every method's jobs measured round-robin on the same inputs."""

from __future__ import annotations

import math
import statistics
import time

import numpy as np

from ..core.landmarks import l2_normalize


def interleaved_times(jobs: dict, repeats: int = 3) -> dict:
    """Wall times of many jobs measured round-robin, so a burst of load from another process hits
    every method alike (a shared CPU is noisy). jobs: name -> list of (callable, divisor). Each
    callable runs once to warm up, then `repeats` rounds; returns name -> median over its callables
    of (best round time / divisor), in ms."""
    for calls in jobs.values():
        for fn, _ in calls:
            fn()
    best = {name: [math.inf] * len(calls) for name, calls in jobs.items()}
    width = max((len(c) for c in jobs.values()), default=0)
    for _ in range(max(1, int(repeats))):
        for i in range(width):
            for name, calls in jobs.items():
                if i < len(calls):
                    t = time.perf_counter()
                    calls[i][0]()
                    best[name][i] = min(best[name][i], time.perf_counter() - t)
    return {name: median_ms([b / d for b, (_, d) in zip(best[name], jobs[name])]) for name in jobs}


def extraction_job(extractor, image: np.ndarray, holistic: bool = False):
    """One full extraction of an original-size RGB image: resize, backbone, head, selection
    (holistic: resize, backbone, global max pool, no head)."""
    from ..io.image import resize_for_network

    if not holistic:
        return lambda: extractor(image)

    def run():
        net = resize_for_network(image, int(extractor.conf['input_height']))
        f = extractor.backbone_features(net[None])[0]
        l2_normalize(f.flatten(1).amax(dim=1).numpy())

    return run


def median_ms(times) -> float:
    return float(statistics.median(times) * 1e3) if times else float('nan')

"""The in-memory FAISS index of the keyframes' global descriptors (the holistic first stage);
the landmark index is lln_ros/core/landmark_index.py, kept in step with the stored keyframes by
landmark_disagreements."""

from __future__ import annotations

import logging

import faiss
import numpy as np

from ..core.landmark_index import held_count
from ..core.threads import one_faiss_thread

log = logging.getLogger(__name__)


class GlobalIndex:
    """The in-memory FAISS index of the global descriptors (D,), keyed by keyframe id, inner product.

    Exact (IndexIDMap(IndexFlatIP)) up to conf['index_threshold'] keyframes; above it an IVF index
    (IndexIVFFlat, trained on the descriptors it is built from, conf['ivf_lists'] cells, searching
    conf['ivf_nprobe'] of them). Crossing the threshold while adding rebuilds it once as IVF.
    """

    def __init__(self, dim: int, conf: dict):
        self.dim, self.conf = int(dim), conf
        self.index = faiss.IndexIDMap(faiss.IndexFlatIP(self.dim))

    @property
    def kind(self) -> str:
        return 'ivf' if isinstance(self.index, faiss.IndexIVF) else 'exact'

    @property
    def ntotal(self) -> int:
        return int(self.index.ntotal)

    def build(self, x: np.ndarray, ids: np.ndarray) -> None:
        """Replace the contents with x (N, D) float32 under ids (N,) int64, choosing the index type."""
        x, ids = np.ascontiguousarray(x, np.float32).reshape(-1, self.dim), np.asarray(ids, np.int64)
        if len(ids) > self.conf['index_threshold']:
            # FAISS wants >= 39 training points per cell; 64 per cell keeps k-means (the bulk of a
            # 100k map's cold start) to about a second
            lists = int(self.conf['ivf_lists']) or max(1, min(int(np.sqrt(len(ids))), len(ids) // 39))
            index = faiss.IndexIVFFlat(faiss.IndexFlatIP(self.dim), self.dim, lists, faiss.METRIC_INNER_PRODUCT)
            index.cp.max_points_per_centroid = 64
            index.train(x)
            index.nprobe = int(self.conf['ivf_nprobe'])
        else:
            index = faiss.IndexIDMap(faiss.IndexFlatIP(self.dim))
        if len(ids):
            index.add_with_ids(x, ids)
        self.index = index

    def add(self, x: np.ndarray, ids: np.ndarray) -> None:
        if self.kind == 'exact' and self.ntotal + len(ids) > self.conf['index_threshold']:
            old_x = self.index.index.reconstruct_n(0, self.ntotal) if self.ntotal else np.zeros((0, self.dim))
            self.build(
                np.concatenate([old_x, np.asarray(x, np.float32).reshape(-1, self.dim)]),
                np.concatenate([faiss.vector_to_array(self.index.id_map), np.asarray(ids, np.int64)]),
            )
            log.info('global index passed %d keyframes: now IVF', self.conf['index_threshold'])
            return
        self.index.add_with_ids(np.ascontiguousarray(x, np.float32).reshape(-1, self.dim), np.asarray(ids, np.int64))

    def remove(self, ids) -> None:
        self.index.remove_ids(np.asarray(list(ids), np.int64))

    def reset(self) -> None:
        self.index = faiss.IndexIDMap(faiss.IndexFlatIP(self.dim))

    def search(self, q: np.ndarray, k: int, below: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Top k (scores (k',), ids (k',)) for one query q (D,), only ids < below when given."""
        params = None
        if below is not None:
            selector = faiss.IDSelectorRange(0, int(below))
            params = (
                faiss.SearchParametersIVF(sel=selector, nprobe=self.index.nprobe)
                if self.kind == 'ivf'
                else faiss.SearchParameters(sel=selector)
            )
        with one_faiss_thread():  # one query: FAISS's threads only wait (core.threads)
            scores, ids = self.index.search(
                np.ascontiguousarray(q, np.float32).reshape(1, self.dim), int(k), params=params
            )
        keep = ids[0] >= 0
        return scores[0][keep], ids[0][keep]

    def ids(self) -> list[int]:
        """Every id in the index, sorted (for the consistency check against SQLite)."""
        if self.kind == 'exact':
            return sorted(faiss.vector_to_array(self.index.id_map).tolist())
        lists = self.index.invlists
        out = []
        for cell in range(lists.nlist):
            size = lists.list_size(cell)
            if size:
                out.extend(faiss.rev_swig_ptr(lists.get_ids(cell), size).tolist())
        return sorted(out)


def landmark_disagreements(index, stored: dict) -> dict[int, tuple[int, int]]:
    """Where a LandmarkIndex and the stored keyframes {keyframe id: landmarks stored} disagree:
    {keyframe id: (landmarks held, landmarks due)} in id order; due = held_count(n, index.conf), 0 for a
    keyframe not stored. Both backends catch up from it at open (held > 0: stale, removed; due > 0:
    missing, added again) and the integrity check reports it (MapStore._landmark_problems)."""
    held = index.keyframe_counts()
    due = {i: held_count(n, index.conf) for i, n in stored.items()}
    both = sorted(held.keys() | due.keys())
    return {i: (held.get(i, 0), due.get(i, 0)) for i in both if held.get(i, 0) != due.get(i, 0)}


def stale_and_missing(wrong: dict) -> tuple[list[int], list[int]]:
    """landmark_disagreements' keyframes to remove from the index (it holds some) and to add (some are due)."""
    return [i for i, (held, _) in wrong.items() if held], [i for i, (_, due) in wrong.items() if due]

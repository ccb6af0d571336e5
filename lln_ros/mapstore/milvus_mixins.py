"""Two parts of MilvusMapStore (milvus.py), as mixins: the open's one read of every row (id list,
integrity check and quarantine, read cache, landmark index and this machine's file of it), and the
keypoints of verify mode."""

from __future__ import annotations

import hashlib
import logging
import os
import time
import uuid

import numpy as np

from ..core import landmark_index
from ..errors import DescriptorError, MapError
from .index import landmark_disagreements, stale_and_missing
from .milvus_rows import _PIECES, compact_row, pack, row_problem, unpack

log = logging.getLogger(__name__.rsplit('_', 1)[0])  # lln_ros.mapstore.milvus, as the backend logs


def landmark_file(label: str, where: str) -> str:
    """This machine's landmark index file of the map labelled `label` (MilvusMapStore.path) in
    directory `where` (conf['landmark_dir']); '' when where is ''. About (PQ m + 8) bytes a landmark."""
    where = os.path.expanduser(where or '')
    return where and os.path.join(where, hashlib.sha1(label.encode()).hexdigest()[:24] + '.landmarks')


class MilvusLandmarks:
    """The open's read of every row and the landmark index (state: MilvusMapStore's)."""

    def _quarantine(self, bad: dict) -> None:
        """Take damaged keyframes {id: problem} out of service: out of the id list and the landmark
        index, never answered; left in the collection (lln-map check names them)."""
        self._quarantined.update(bad)
        self._ids = [i for i in self._ids if i not in bad]
        self._cache.drop(bad)
        if self._landmarks is not None:
            self._landmarks.remove_keyframes(sorted(bad))
            self._landmarks_dirty = True
        log.warning(
            'map %s: %d damaged keyframe(s) quarantined (kept in the map, never answered): %s',
            self.path,
            len(bad),
            '; '.join(list(bad.values())[:10]),
        )

    def _scan_rows(self):
        """Every row of the frames collection in id order, as lists of compact rows (256 per reply),
        read at one timestamp: a query iterator takes the newest at its start (one wait, as Strong)."""
        it = self._client.query_iterator(
            self._fr_c, batch_size=256, filter='id >= 0', output_fields=['*'], consistency_level='Strong'
        )
        try:
            while rows := it.next():
                yield [compact_row(r) for r in rows]
        finally:
            it.close()

    def _load_landmarks(self) -> None:
        """One read of every row: the id list, the integrity check (damaged keyframes quarantined),
        the read cache and the landmark index (local FAISS: this machine's file of it caught up
        with the rows, or built from them)."""
        kept = self._read_landmark_file()
        self._landmarks = kept or self._new_landmark_index()
        self._ids, dim, bad, stored = [], int(self._model['descriptor_dim']), {}, {}
        for rows in self._scan_rows():
            good = []
            for row in rows:
                if row['id'] in self._deleted:
                    continue
                problem = row_problem(row, dim)
                if problem:
                    bad[row['id']] = problem
                else:
                    good.append(row)
                    stored[row['id']] = int(row['n'])
                    self._cache.put(row)
            self._ids.extend(r['id'] for r in good)
        self._ids.sort()
        if kept is None:
            self._build_landmarks(self._held_total(stored))
            self._landmarks_dirty = self._landmarks.kind != 'exact'
        else:
            stale, missing = stale_and_missing(landmark_disagreements(kept, stored))
            kept.remove_keyframes(stale)
            self._index_landmarks(missing)
            self._landmarks_dirty = bool(stale or missing)
            self._retrain_if_needed()
        if bad:
            self._quarantine(bad)

    def _build_landmarks(self, total: int) -> None:
        """The landmark index of the keyframes in _ids (total landmarks), sized for all of them: above
        the threshold one IVF-PQ trained once on a sample (every k-th keyframe, ~landmark_train_points
        landmarks), as the SQLite backend builds it; fed row by row it was trained on the first rows
        and trained again as they came, with fewer IVF lists: every query scanned more codes."""
        index = self._new_landmark_index()
        if total > self.conf['landmark_index_threshold']:
            pick, parts = self._ids[:: index.train_stride(total)], []
            for start in range(0, len(pick), 512):  # from the read cache (the rows were just read)
                parts += [
                    index.prepare(s.descriptors, held=True) for s in self._fetch(pick[start : start + 512]).values()
                ]
            index.train(parts, total)
        self._landmarks = index
        self._index_landmarks(self._ids)

    def _retrain_if_needed(self) -> None:
        """Train the IVF-PQ again, sized for every keyframe, once it holds landmark_retrain_factor x
        what it was trained on (as the SQLite backend does): its lists overfill and every query
        scans more (bench_milvus_server.py, 10k keyframes on an index trained at 1k: its search alone
        took 71 ms a query, SQLite's whole query 43 ms p50)."""
        if self._landmarks is None or not self._landmarks.needs_rebuild():
            return
        t = time.perf_counter()
        self._build_landmarks(self._landmarks.ntotal)
        self._landmarks_dirty = True
        log.info(
            'map %s: landmark index retrained for %d landmarks (%.1f s)',
            self.path,
            self._landmarks.ntotal,
            time.perf_counter() - t,
        )

    def _landmark_file(self) -> str:
        return landmark_file(self.path, self.conf['landmark_dir'])

    def _read_landmark_file(self):
        """This machine's landmark index of this map (LandmarkIndex), or None: none, unusable, or
        of another map (its map_uuid differs: a map dropped and made again under the same name)."""
        path = self._landmark_file()
        if not path or not self._uuid or not os.path.exists(path):
            return None
        try:
            index, header = landmark_index.LandmarkIndex.read(
                path, int(self._model['descriptor_dim']), self.conf, self._model['descriptor_space']
            )
        except MapError as e:
            log.warning('map %s: %s; rebuilding it from the map', self.path, e)
            return None
        return index if header.get('map_uuid') == self._uuid else None

    def _persist_landmarks(self) -> None:
        """Write the landmark index to this machine's file when it is trained (IVF-PQ) and changed."""
        path = self._landmark_file()
        if not path or self._landmarks is None or self._landmarks.kind == 'exact' or not self._landmarks_dirty:
            return
        if not self._uuid:  # a map made before map_uuid existed
            self._uuid = uuid.uuid4().hex
            self._put_meta({'map_uuid': self._uuid})
        try:
            os.makedirs(os.path.dirname(path), exist_ok=True)
        except OSError as e:
            raise MapError(f'map {self.path}: cannot keep its landmark index in {path}: {e}') from e
        self._landmarks.write(path, {'map_uuid': self._uuid, 'map': self.path})
        self._landmarks_dirty = False

    def _index_landmarks(self, ids) -> None:
        for start in range(0, len(ids), 512):
            sets = self._fetch(ids[start : start + 512])
            self._landmarks.add_sets(list(sets), list(sets.values()))


class MilvusKeypoints:
    """verify mode's keypoints in the {map}_keypoints collection (state: MilvusMapStore's)."""

    def add_keypoints(self, keyframe_id: int, uv: np.ndarray, descriptors: np.ndarray) -> None:
        """Store a keyframe's keypoints (as SQLiteMapStore.add_keypoints): uv (N, 2) float32 original
        pixels, binary descriptors (N, B) uint8; replaces earlier ones."""
        uv = np.ascontiguousarray(uv, '<f4').reshape(-1, 2)
        desc = np.ascontiguousarray(descriptors)
        if desc.dtype != np.uint8 or desc.ndim != 2 or len(desc) != len(uv):
            raise DescriptorError(
                f'keypoints need (N, B) uint8 descriptors for N={len(uv)} points, got {desc.dtype} {desc.shape}'
            )
        row = {
            'keyframe_id': int(keyframe_id),
            'n': len(uv),
            'width': int(desc.shape[1]),
            'data': pack(uv, desc),
            'unused': [0.0, 0.0],
        }
        with self._lock, self._errors('storing keypoints'):
            self._ready()
            if int(keyframe_id) not in set(self._ids):
                raise KeyError(f'no keyframe {keyframe_id} in map {self.path}')
            if not self._has_keypoints and not self._client.has_collection(self._kp_c):
                from pymilvus import DataType

                self._create(
                    self._kp_c,
                    [
                        ('keyframe_id', 'INT64', {'is_primary': True}),
                        ('n', 'INT32', {}),
                        ('width', 'INT32', {}),
                        (
                            'data',
                            'ARRAY',
                            {'element_type': DataType.VARCHAR, 'max_capacity': _PIECES, 'max_length': 65535},
                        ),
                    ],
                    'unused',
                    2,
                )
            self._has_keypoints = True
            self._client.upsert(self._kp_c, [row])

    def keypoints(self, keyframe_id: int) -> tuple[np.ndarray, np.ndarray] | None:
        """(uv (N, 2) float32, descriptors (N, B) uint8) of a keyframe, or None when none were stored."""
        with self._lock, self._errors('reading keypoints'):
            self._ready()
            if not self._has_keypoints:
                return None
            rows = self._client.query(
                self._kp_c, filter=f'keyframe_id == {int(keyframe_id)}', output_fields=['n', 'width', 'data']
            )
        if not rows:
            return None
        n, width, blob = int(rows[0]['n']), int(rows[0]['width']), unpack(rows[0]['data'])
        if len(blob) != n * (8 + width):
            raise MapError(
                f'map {self.path} is corrupt: keyframe {keyframe_id} keypoints are {len(blob)} bytes '
                f'for n={n}, width {width}'
            )
        return (
            np.frombuffer(blob, '<f4', 2 * n).reshape(n, 2).copy(),
            np.frombuffer(blob, np.uint8, n * width, 8 * n).reshape(n, width).copy(),
        )

"""The SQLite map's landmark index: rebuilt, or loaded from <map>.landmarks and reconciled with the
keyframes table, persisted when compressed (a mixin of SQLiteMapStore)."""

from __future__ import annotations

import logging
import os
import uuid

import numpy as np

from ..core.landmark_index import LandmarkIndex
from ..errors import MapError
from .index import landmark_disagreements, stale_and_missing
from .sqlite_file import _SQL_CHUNK

log = logging.getLogger(__name__)


class SQLiteLandmarks:
    """SQLiteMapStore's landmark index upkeep (reads its path, conf, _conn, _model, _landmarks)."""

    # ------------------------------------------------------------------ the landmark index
    # Exact (below conf['landmark_index_threshold'] landmarks): rebuilt from the landmarks table at
    # every open, like the global index. IVF-PQ (above): trained once, persisted in
    # `<map>.landmarks` by save() and close(), loaded at open and reconciled with the keyframes
    # table (keyframes added after the last save are added, deleted ones removed), rebuilt from
    # SQLite when the file is missing, corrupt or from another map (meta map_uuid).

    def _stored_counts(self) -> dict[int, int]:
        """{keyframe id: n} the landmark index must hold (corrupt keyframes it cannot hold excluded)."""
        return {
            int(i): int(n)
            for i, n in self._conn.execute('SELECT id, n FROM keyframes')
            if int(i) not in self._unindexed
        }

    def _landmark_rows(self, ids=None, every: int = 1):
        """Landmarks of the given keyframes (None = all; every: only ids divisible by it) in chunks:
        (keyframe ids (m,), cells (m, 2), descriptors (m, D) float32)."""
        dim = int(self._model['descriptor_dim'])
        if ids is None:
            chunks = [None]
        else:
            ids = sorted(int(i) for i in ids)
            chunks = [ids[i : i + _SQL_CHUNK] for i in range(0, len(ids), _SQL_CHUNK)]
        for chunk in chunks:
            where = (
                f'WHERE k.id IN ({",".join("?" * len(chunk))})'
                if chunk is not None
                else (f'WHERE k.id % {int(every)} = 0' if every > 1 else '')
            )
            with self._read_errors():  # the join: orphan landmark rows are check()'s business, not the index's
                cursor = self._conn.execute(
                    'SELECT k.id, l.cells, l.descriptors FROM keyframes k JOIN landmarks l '
                    f'ON l.keyframe_id = k.id {where} ORDER BY k.id',
                    chunk or (),
                )
                while rows := cursor.fetchmany(512):
                    kf, cells, desc = [], [], []
                    for kid, c, d in rows:
                        if int(kid) in self._unindexed:  # quarantined at open (e.g. a bad stamp, good blobs)
                            continue
                        n = len(c) // 4
                        if len(c) != 4 * n or len(d) != 2 * n * dim:
                            # not indexed, and named: check() reports it, a query that fetches it raises
                            log.error(
                                'map %s is corrupt: keyframe %d landmark blobs are %d + %d bytes (D=%d)',
                                self.path,
                                kid,
                                len(c),
                                len(d),
                                dim,
                            )
                            self._unindexed.add(int(kid))
                            continue
                        if n == 0:
                            continue
                        kf.append(np.full(n, kid, np.int64))
                        cells.append(np.frombuffer(c, '<i2').reshape(n, 2))
                        desc.append(np.frombuffer(d, '<f2').reshape(n, dim))
                    if kf:
                        yield np.concatenate(kf), np.concatenate(cells), np.concatenate(desc).astype(np.float32)

    def _map_uuid(self, create: bool = False) -> str | None:
        uid = self._meta().get('map_uuid')
        if uid is None and create:
            uid = uuid.uuid4().hex
            self._write(lambda c: c.execute("INSERT OR IGNORE INTO meta (key, value) VALUES ('map_uuid', ?)", (uid,)))
            uid = self._meta()['map_uuid']
        return uid

    def _load_landmarks(self) -> None:
        self._unindexed: set[int] = set(self._quarantined)  # damaged at open: never indexed or answered
        stored = self._stored_counts()
        total = self._held_total(stored)
        index, why = None, 'missing'
        if total > self.conf['landmark_index_threshold'] and os.path.exists(self.landmark_path):
            try:
                index, header = LandmarkIndex.read(
                    self.landmark_path, int(self._model['descriptor_dim']), self.conf, self._model['descriptor_space']
                )
                if header.get('map_uuid') != self._map_uuid():
                    index, why = None, 'from another map'
            except MapError as e:
                index, why = None, str(e)
        if index is not None:
            stale, missing = stale_and_missing(landmark_disagreements(index, stored))
            index.remove_keyframes(stale)
            for kf, cells, desc in self._landmark_rows(missing):
                index.add(desc, kf, cells)
            self._landmarks_dirty = bool(stale or missing)
            # nothing to catch up: the comparison above was the consistency check (each of its
            # keyframe_counts() took 0.16-0.20 s of a 100k-keyframe map's cold start)
            checked = not self._landmarks_dirty
            if stale or missing:
                log.info(
                    'map %s: landmark index caught up (%d keyframes added, %d removed)',
                    self.path,
                    len(missing),
                    len(stale),
                )
        else:
            if total > self.conf['landmark_index_threshold']:
                log.warning(
                    'map %s: landmark index %s (%s); rebuilding it from the map (%d landmarks)',
                    self.path,
                    self.landmark_path,
                    why,
                    total,
                )
            index = self._build_landmarks(total, len(stored))
            self._landmarks_dirty = index.kind != 'exact'
            checked = False
        self._landmarks = index
        problems = [] if checked else self._landmark_problems(self._stored_counts())
        if problems:
            raise MapError(f'map {self.path}: {"; ".join(problems)}')
        if index.kind == 'exact':
            self._drop_landmark_file()

    def _build_landmarks(self, total: int, keyframes: int) -> LandmarkIndex:
        index = self._new_landmark_index()
        if total > self.conf['landmark_index_threshold']:
            # train on a sample of keyframes, then stream every landmark in
            every = index.train_stride(total)
            index.train([index.prepare(d, kf, held=True) for kf, _, d in self._landmark_rows(every=every)], total)
        for kf, cells, desc in self._landmark_rows():
            index.add(desc, kf, cells)  # prepared and encoded as every add; trained above, so no retrain here
        return index

    def _persist_landmarks(self) -> None:
        if self._landmarks is None or self._landmarks.kind == 'exact' or not self._landmarks_dirty:
            return
        self._landmarks.write(self.landmark_path, {'map_uuid': self._map_uuid(create=True)})
        self._landmarks_dirty = False

    def _drop_landmark_file(self) -> None:
        try:
            os.remove(self.landmark_path)
        except FileNotFoundError:
            pass
        except OSError as e:
            log.warning('map %s: cannot remove %s: %s', self.path, self.landmark_path, e)

    def _faiss_problems(self) -> list[str]:
        ids = [
            r[0] for r in self._conn.execute('SELECT id FROM keyframes ORDER BY id') if r[0] not in self._quarantined
        ]
        if self._index is None:
            return [f'no FAISS index but {len(ids)} keyframes'] if ids else []
        problems = []
        if self._index.ntotal != len(ids):
            problems.append(f'FAISS index holds {self._index.ntotal} keyframes, SQLite {len(ids)}')
        faiss_ids = self._index.ids()
        if faiss_ids != ids or self._ids != ids:
            only_f, only_s = sorted(set(faiss_ids) - set(ids)), sorted(set(ids) - set(faiss_ids))
            problems.append(
                f'FAISS and SQLite keyframe ids differ (only in FAISS: {only_f[:10]}, only in SQLite: {only_s[:10]})'
            )
        return problems

"""The SQLite map's reader catching up with another process's new keyframes (a mixin of SQLiteMapStore).

When another connection commits (`PRAGMA data_version` moves), the in-memory FAISS indexes are
stale. A full reload rebuilds both from the file, and above `landmark_index_threshold` that
retrains the compressed landmark index: 82 times in each matcher of bench_fleet's two-robot run,
at up to 88k landmarks. What writers do is append, so the common case is read incrementally: the
new ids' rows are added to the indexes, as the writer's own add_many adds them (ids below ours
too: another writer's, interleaved with ours, or an import that keeps ids). Anything else falls
back to the full reload: another model record, a keyframe gone (delete, clear, a restore), a
damaged row, new or not (the reload quarantines it). Not seen: a foreign tool rewriting a held
keyframe's blobs in place with valid sizes (lln_ros never updates a keyframe; VACUUM keeps ids
and contents).
"""

from __future__ import annotations

import logging

import numpy as np

log = logging.getLogger(__name__)


class SQLiteCatchUp:
    """SQLiteMapStore's incremental reload (uses _conn, _model, _ids, _quarantined, _index, _landmarks)."""

    def _catch_up(self) -> bool:
        """Add the keyframes other processes appended since our snapshot; False: reload in full."""
        if self._model is None or self._index is None or self._landmarks is None:
            return False
        c = self._conn
        own = not c.in_transaction
        if own:
            c.execute('BEGIN')  # one snapshot for every read below (as _load)
        try:
            return self._catch_up_snapshot()
        finally:
            if own and c.in_transaction:
                c.execute('COMMIT')

    def _catch_up_snapshot(self) -> bool:
        c = self._conn
        version = c.execute('PRAGMA data_version').fetchone()[0]
        meta = self._meta()
        if 'model' not in meta or self._read_model_record(meta['model']) != self._model:
            return False
        known = set(self._ids) | set(self._quarantined)
        ids = {int(r[0]) for r in c.execute('SELECT id FROM keyframes')}  # ints: ~20 ms at 100k
        if not known <= ids:  # one is gone (delete, clear, a restored file)
            return False
        # not only above our highest id: two writers interleave, so the other's keyframe can sit below
        # one we stored ourselves
        new = sorted(ids - known)
        # damage anywhere, also to a keyframe we hold (another connection wrote it): the reload
        # quarantines it. One length() scan (0.87 s at 100k keyframes, milliseconds at 1k)
        if set(self._damaged(int(self._model['descriptor_dim']))) - set(self._quarantined):
            return False
        if new:
            sets = self._fetch(new)
            ordered = [sets[i] for i in new]
            self._index.add(np.stack([s.global_descriptor for s in ordered]).astype(np.float32), np.asarray(new))
            self._landmarks.add_sets(new, ordered)
            self._landmarks_dirty = self._landmarks_dirty or self._landmarks.kind != 'exact'
            if self._landmarks.needs_rebuild():  # the same retrain the writer's add_many does
                stored = self._stored_counts()
                self._landmarks = self._build_landmarks(self._held_total(stored), len(stored))
            self._ids = sorted(self._ids + new)
            log.info('map %s: %d keyframes of another process added to the indexes', self.path, len(new))
        self._data_version = version
        return True

"""A part of MilvusMapStore (milvus.py), as a mixin: numbers that many writers of one map take
without colliding, with no transactions (Milvus 2.3 has none and does not enforce primary-key
uniqueness), and following the other writers' keyframes (_refresh). Schema 5 (issue 29, part 3).

    {map}_claims  claim VARCHAR primary ('kind/number/owner'), kind INT64, number INT64,
                  owner VARCHAR (the claiming store's random token), unused FLOAT_VECTOR(2)

kind: KIND_BLOCK (a block of keyframe ids a writer allocates from), KIND_SESSION (a session
number), KIND_IMPORT (a block that keyframes with given ids, an import, were written into).

To take a number a writer inserts its claim for the largest claimed number + 1, then reads every
claim of that number with Strong consistency: it owns the number only if its claim is the only one.
Otherwise it leaves its claim (a number is never used twice, so a claim is never taken back) and
tries a higher number after a short random wait. Of two writers claiming one number, the later
insert's read (Strong: it sees every write acknowledged before it started) sees the earlier claim,
so at most one of them owns it; both may lose, and retry. The primary key is unique per claim
because Milvus keeps duplicate primary keys but a query returns only one of them (measured on the
2.3.5 server): a claims table keyed by the number would hide the rival claim.

Keyframe ids: block b holds [max(b * ID_BLOCK, floor), (b + 1) * ID_BLOCK), floor = the meta record's
next_id (1 in a new map; in a map of schema 4 the ids its one writer had reserved). A writer claims
a block at its first add and the next when it is used up; ids are handed out in order within it, so
ids are unique but not dense: the writers' blocks interleave, a stopped writer leaves the rest of
its block unused. A session number is a claimed KIND_SESSION number above every session stored.
"""

from __future__ import annotations

import bisect
import logging
import random
import secrets
import time

from ..errors import MapError
from .milvus_rows import _QUERY_ROWS

log = logging.getLogger(__name__.rsplit('_', 1)[0])  # lln_ros.mapstore.milvus, as the backend logs

ID_BLOCK = 1024  # keyframe ids per claimed block
KIND_BLOCK, KIND_SESSION, KIND_IMPORT = 0, 1, 2
CLAIM_TRIES = 50  # attempts at a number before a MapError (each loses only to another writer's claim)
WATCHED_WRITERS = 32  # a refresh asks for new ids in the open blocks of this many other writers;
# older ones are caught by the count check (a rescan of the id list)


def _name(store) -> str:
    return store._fr_c[: -len('_frames')] + '_claims'


def create_claims(store) -> None:
    name = _name(store)
    if not store._client.has_collection(name):
        fields = [
            ('claim', 'VARCHAR', {'is_primary': True, 'max_length': 128}),
            ('kind', 'INT64', {}),
            ('number', 'INT64', {}),
            ('owner', 'VARCHAR', {'max_length': 64}),
        ]
        store._create(name, fields, 'unused', 2)
    store._load_ready(name)


def migrate_4_to_5(store, meta: dict) -> None:
    """Schema 4 -> 5: the claims collection. The map's next_id (what its one writer had reserved)
    stays the floor of the ids in new blocks; its sessions' numbers the floor of new sessions."""
    create_claims(store)


class MilvusClaims:
    """Claimed id blocks and session numbers, and the refresh that follows other writers (state:
    MilvusMapStore's; _owner, _floor, _next_id, _reserved, _claims_seen are this part's)."""

    def _claims_init(self) -> None:
        self._owner = secrets.token_hex(16)  # this store's claims (a new one at every open)
        self._floor = 1  # the meta record's next_id: no block gives an id below it
        self._next_id = self._reserved = 0  # the id block this store allocates from: none yet
        self._writers: dict[str, int] = {}  # other writers' newest claimed block (refresh)
        self._claims_seen = -1

    def _claims_ready(self) -> str:
        client = self._client
        if getattr(self, '_claims_client', None) is not client:  # a new client (open, reconnect): load it
            create_claims(self)
            self._claims_client = client
        return _name(self)

    def _claims(self, where: str, fields=('number', 'owner', 'kind'), strong: bool = True) -> list[dict]:
        """Claims matching `where`; strong=False: the collection's consistency (a refresh: a Strong read
        waits ~0.4 s, and a claim seen a refresh later only delays a watch the count check backs up)."""
        return self._client.query(
            self._claims_ready(),
            filter=where,
            output_fields=list(fields),
            limit=_QUERY_ROWS,
            **({'consistency_level': 'Strong'} if strong else {}),
        )

    def _top_claim(self, kinds: tuple[int, ...]) -> int:
        """The largest number claimed of these kinds, -1 when none."""
        top = -1
        while True:
            rows = self._claims(f'kind in {list(kinds)} and number > {top}', ('number',))
            if not rows:
                return top
            top = max(top, max(int(r['number']) for r in rows))
            if len(rows) < _QUERY_ROWS:
                return top

    def _insert_claim(self, kind: int, number: int) -> None:
        row = {'claim': f'{kind}/{number}/{self._owner}', 'kind': kind, 'number': number}
        self._client.insert(self._claims_ready(), [{**row, 'owner': self._owner, 'unused': [0.0, 0.0]}])

    def _claim(self, kind: int, first: int) -> int:
        """A number >= first that no other writer will ever own (see the module docstring)."""
        kinds = (KIND_BLOCK, KIND_IMPORT) if kind == KIND_BLOCK else (kind,)
        number = max(first, self._top_claim(kinds) + 1)
        for attempt in range(CLAIM_TRIES):
            self._insert_claim(kind, number)
            rivals = [
                r for r in self._claims(f'kind in {list(kinds)} and number == {number}') if r['owner'] != self._owner
            ]
            if not rivals:
                return number
            log.info('map %s: claim %d/%d lost to another writer; trying a higher one', self.path, kind, number)
            time.sleep(random.uniform(0.0, 0.02 * 2 ** min(attempt, 5)))
            number = max(number + 1, self._top_claim(kinds) + 1)
        raise MapError(f'map {self.path}: no free number of kind {kind} after {CLAIM_TRIES} claims (too many writers?)')

    def _allocate(self, n: int) -> list[int]:
        """n new keyframe ids from this store's block, claiming blocks as needed. Consumed here, before
        the insert: an insert that fails (perhaps after the server stored part of it) skips them."""
        out: list[int] = []
        while len(out) < n:
            if self._next_id >= self._reserved:
                block = self._claim(KIND_BLOCK, self._floor // ID_BLOCK)
                self._next_id, self._reserved = max(block * ID_BLOCK, self._floor), (block + 1) * ID_BLOCK
            take = min(n - len(out), self._reserved - self._next_id)
            out.extend(range(self._next_id, self._next_id + take))
            self._next_id += take
        return out

    def _claim_given(self, ids: list[int]) -> None:
        """Given ids (an import keeping ids): refused when they lie in a block another writer allocates
        from; their blocks are claimed (KIND_IMPORT) so that no writer allocates from them later."""
        for block in sorted({i // ID_BLOCK for i in ids if i >= self._floor}):
            if self._reserved and block == (self._reserved - 1) // ID_BLOCK:  # this store's own block
                self._next_id = max(self._next_id, max(i for i in ids if i // ID_BLOCK == block) + 1)
                continue
            self._insert_claim(KIND_IMPORT, block)
            rows = self._claims(f'kind == {KIND_BLOCK} and number == {block}')
            if any(r['owner'] != self._owner for r in rows):
                raise MapError(
                    f'map {self.path}: keyframe ids {block * ID_BLOCK}-{(block + 1) * ID_BLOCK - 1} are a block '
                    f'another writer allocates from; keep ids elsewhere or merge (new ids)'
                )

    def _check_claimed(self, last: int) -> None:
        """At open: every stored id lies below the floor or in a claimed block."""
        if last >= self._floor and last // ID_BLOCK > self._top_claim((KIND_BLOCK, KIND_IMPORT)):
            raise MapError(f'map {self.path} is damaged: keyframe {last} lies in no claimed id block')

    def _watch(self, known: set) -> list[str]:
        """Filter clauses for new ids in the open blocks of other writers, below the largest id known
        (above it `id > top` finds them): a writer fills only its newest claimed block, in id order."""
        rows = self._claims(f'kind == {KIND_BLOCK} and number > {self._claims_seen}', strong=False)
        for r in rows:
            if r['owner'] != self._owner:
                self._writers[r['owner']] = max(self._writers.get(r['owner'], -1), int(r['number']))
            self._claims_seen = max(self._claims_seen, int(r['number']))
        ids, top, clauses = self._ids, max(known, default=-1), []  # _ids is sorted
        for block in sorted(self._writers.values())[-WATCHED_WRITERS:]:
            lo, hi = max(block * ID_BLOCK, self._floor), (block + 1) * ID_BLOCK
            if lo > top:
                continue
            j = bisect.bisect_left(ids, hi)
            last = ids[j - 1] if j and ids[j - 1] >= lo else lo - 1
            if last < hi - 1:
                clauses.append(f'(id > {last} and id < {hi})')
        return clauses

    def _refresh(self) -> None:
        """See other processes' writes: new ids above ours and in other writers' open blocks, a
        rescan when the count disagrees (deletes, imports, writers the watch leaves out)."""
        self._refreshed = time.monotonic()
        try:
            with self._errors('refresh'):
                if self._model is None:
                    meta = self._meta()
                    if 'model' not in meta:
                        return
                    self._model = self._read_model_record(meta['model'])
                    if not self._client.has_collection(self._fr_c):
                        return
                    self._load_ready(self._fr_c)
                before = set(self._ids)
                known = before | set(self._quarantined) | self._deleted
                where = ' or '.join([f'id > {max(known, default=-1)}'] + self._watch(known))
                new = self._client.query(self._fr_c, filter=where, output_fields=['id'], limit=_QUERY_ROWS)
                self._ids = sorted(before | ({int(r['id']) for r in new} - known))
                count = int(self._client.query(self._fr_c, filter='', output_fields=['count(*)'])[0]['count(*)'])
                if count != len(self._ids) + len(self._quarantined) or len(new) == _QUERY_ROWS:
                    self._ids = sorted(set(self._scan_ids()))
                    present = set(self._ids)  # a quarantined keyframe another process deleted is gone
                    self._quarantined = {k: v for k, v in self._quarantined.items() if k in present}
                if self._deleted or self._quarantined:
                    self._ids = [i for i in self._ids if i not in self._deleted and i not in self._quarantined]
                self._follow(before)
        except MapError as e:  # a reader keeps answering from the ids it has
            log.warning('%s', e)

    def _follow(self, before: set) -> None:
        """Another process's keyframes reach this process's landmark index and read cache too."""
        now = set(self._ids)
        if self._landmarks is None:
            self._load_landmarks()
        elif now != before:
            self._landmarks.remove_keyframes(sorted(before - now))
            self._cache.drop(before - now)
            self._index_landmarks(sorted(now - before))
            self._landmarks_dirty = True
            self._retrain_if_needed()
        if not self._has_keypoints:
            self._has_keypoints = self._client.has_collection(self._kp_c)

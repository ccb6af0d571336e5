"""The Milvus backend's row format and plumbing (milvus.py): URIs, the base64 pieces of a row's
bytes, the compact cached form of a frames row, its integrity check, the read cache, error text.

Read cache: a stored keyframe is never rewritten (ids are never reused; only deletes change the map),
so the rows this process has read or written are kept (RowCache, at most conf['cache_mb'], least
recently used dropped first) and a query asks the server only for the candidates it has not seen.
The open reads every row anyway (to build the landmark index), so a map that fits is then served
from memory: the server is the map of record, shared and durable, not the per-query path.

Integrity: every row read (all of them at open) is checked against its declared sizes (row_problem:
landmark bytes = n x (16 + 2 D), n >= 1, grid >= 1x1, stamp nanosec < 1e9). A damaged
keyframe is quarantined, as the SQLite backend does: left in the collection, named in the log and
in ``quarantined`` / info() / check(), never answered; a query never counts it as bad input. The
check costs nothing beyond the open's read of every row (bench/bench_milvus_server.py times it).
"""

from __future__ import annotations

import base64
import os
from collections import OrderedDict
from urllib.parse import parse_qs, urlparse

import numpy as np

from ..core.limits import stamp_problem
from ..errors import DescriptorError, MapError

_PIECE = 65532  # base64 characters per VARCHAR piece: a multiple of 4, <= 65535
_PIECES = 64  # pieces per row (the ARRAY's max_capacity)
_FETCH_IDS = 256  # keyframes per fetch-by-id query: a reply of ~9 MB at n=50, D=320
_QUERY_ROWS = 16384  # Milvus caps offset + limit of one query at 16384 rows
_SCALARS = ('stamp_sec', 'stamp_nanosec', 'image_w', 'image_h', 'cell_w', 'cell_h', 'grid_rows', 'grid_cols', 'n')


def parse_uri(uri: str) -> dict:
    """{'uri', 'db_name', 'map', 'label'} for pymilvus from a milvus:// or milvus-lite:// URI."""
    text = os.fspath(uri)
    if text.startswith('milvus-lite:'):
        path = text[len('milvus-lite:') :]
        path = path[2:] if path.startswith('//') else path
        path, _, query = path.partition('?')
        path = os.path.abspath(os.path.expanduser(path))
        if not path.endswith('.db'):
            raise MapError(f'Milvus Lite map path must end in .db, got {path}')
        name = parse_qs(query).get('map', ['lln'])[0]
        return {'uri': path, 'db_name': '', 'map': name, 'label': f'milvus-lite://{path}?map={name}'}
    url = urlparse(text)
    if url.scheme != 'milvus' or not url.hostname:
        raise MapError(f"Milvus map URI must look like 'milvus://host:port[/database][?map=name]', got {text!r}")
    name = parse_qs(url.query).get('map', ['lln'])[0]
    db = url.path.strip('/')
    endpoint = f'http://{url.hostname}:{url.port or 19530}'
    return {'uri': endpoint, 'db_name': db, 'map': name, 'label': f'milvus://{url.netloc}/{db}?map={name}'}


def pack(*arrays: np.ndarray) -> list[str]:
    """Arrays' bytes, concatenated, as base64 pieces for an ARRAY<VARCHAR> field."""
    text = base64.b64encode(b''.join(a.tobytes() for a in arrays)).decode('ascii')
    if len(text) > _PIECE * _PIECES:
        raise DescriptorError(
            f'{len(text) * 3 // 4} bytes do not fit one Milvus row '
            f'(at most {_PIECE * _PIECES * 3 // 4}); store fewer landmarks or keypoints'
        )
    return [text[i : i + _PIECE] for i in range(0, len(text), _PIECE)] or ['']


def unpack(pieces) -> bytes:
    return base64.b64decode(''.join(pieces))


def compact_row(r: dict) -> dict:
    """A frames row as Milvus returns it -> the cached form: id, the scalars, gd (D,) float32 and
    blob (the landmark bytes; None when the pieces are not base64)."""
    try:
        blob = unpack(r['landmarks'])
    except (ValueError, TypeError):  # binascii.Error is a ValueError
        blob = None
    row = {f: r[f] for f in _SCALARS}
    row.update(id=int(r['id']), gd=np.asarray(r['global_descriptor'], np.float32), blob=blob)
    return row


def row_problem(row: dict, dim: int) -> str | None:
    """What is wrong with a compact row against its declared sizes, or None (the integrity check)."""
    kid, n, blob = row['id'], int(row['n']), row['blob']
    if blob is None:
        return f'keyframe {kid}: landmark blob is not base64'
    want = n * (16 + 2 * dim)
    if n < 1 or len(blob) != want:
        return (
            f'keyframe {kid}: landmark blob size {len(blob)} bytes does not fit n={n}, D={dim} '
            f'(expected {want}: cells 4n + centers 8n + scores 4n + descriptors 2nD)'
        )
    if int(row['grid_rows']) < 1 or int(row['grid_cols']) < 1:
        return f'keyframe {kid}: bad grid {row["grid_rows"]}x{row["grid_cols"]}'
    stamp = stamp_problem(row['stamp_sec'], row['stamp_nanosec'])  # an answer could not carry it
    if stamp:
        return f'keyframe {kid}: {stamp}'
    return None


class RowCache:
    """Compact rows by keyframe id, the least recently used dropped past max_bytes. Needs no
    invalidation from other processes: a stored keyframe is never rewritten, only deleted, and a
    deleted id leaves the id list (and is dropped here) before any query could ask for it."""

    def __init__(self, max_bytes: int):
        self.max_bytes, self.bytes = int(max_bytes), 0
        self._rows: OrderedDict[int, dict] = OrderedDict()

    def __len__(self) -> int:
        return len(self._rows)

    def get(self, kid: int) -> dict | None:
        row = self._rows.get(kid)
        if row is not None:
            self._rows.move_to_end(kid)
        return row

    def put(self, row: dict) -> None:
        if self.max_bytes <= 0:
            return
        self.drop([row['id']])
        row['size'] = len(row['blob']) + row['gd'].nbytes + 600  # + the dict and its scalars
        self._rows[row['id']] = row
        self.bytes += row['size']
        while self.bytes > self.max_bytes:
            self.bytes -= self._rows.popitem(last=False)[1]['size']

    def drop(self, ids) -> None:
        for i in ids:
            row = self._rows.pop(int(i), None)
            if row is not None:
                self.bytes -= row['size']

    def clear(self) -> None:
        self._rows.clear()
        self.bytes = 0


def explain(e: BaseException) -> str:
    """A pymilvus / gRPC error as one line, with what to do for the common ones."""
    code = getattr(e, 'code', None)
    code = code() if callable(code) else code
    text = f'{type(e).__name__}: {getattr(e, "details", lambda: None)() or e}'.replace('\n', ' ')
    if 'RESOURCE_EXHAUSTED' in f'{code} {text}' or 'larger than max' in text:
        text += (
            ' (a gRPC message over the server limit, 64 MB on Milvus 2.3 (grpc.serverMaxRecvSize): '
            "lower conf['insert_bytes'])"
        )
    elif 'UNAVAILABLE' in f'{code} {text}' or 'connect' in text.lower():
        text += ' (is the Milvus server running and reachable?)'
    return text[:800]


def _is_milvus_error(e: BaseException) -> bool:
    mod = type(e).__module__ or ''
    return (
        mod.startswith(('pymilvus', 'grpc', 'milvus_lite'))
        or isinstance(e, (ConnectionError, TimeoutError))
        or any(c.__module__.startswith(('grpc', 'pymilvus')) for c in type(e).__mro__)
    )


def scan_ids(client, collection: str, **query) -> list[int]:
    """Every row id of a collection, sorted (a query iterator: one query returns at most 16,384 rows).
    query: extra query_iterator arguments, e.g. consistency_level='Strong'."""
    it = client.query_iterator(collection, batch_size=4096, filter='id >= 0', output_fields=['id'], **query)
    ids = []
    try:
        while rows := it.next():
            ids.extend(int(r['id']) for r in rows)
    finally:
        it.close()
    return sorted(ids)

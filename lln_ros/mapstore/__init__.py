"""The persistent map behind the matcher node: keyframes' landmark sets, embedded or in Milvus.

    with MapStore.open('~/.ros/lln/map.db', model=extractor.model_info) as store:
        kf = store.add(landmarks, stamp=(sec, nanosec))           # durable when it returns
        for c in store.query(landmarks, exclude_recent=20):       # online loop closure
            c.keyframe_id, c.score, c.stamp, c.pairs['map_u'], ...

No rclpy here: the node wraps this class, tests use it directly. ``MapStore(uri)`` returns the
backend the URI names (backend_for): a plain path is the embedded SQLiteMapStore below;
``milvus://host:port`` and ``milvus-lite:///path.db`` are MilvusMapStore (lln_ros/mapstore/milvus.py).
Both have the API listed in MapStore's docstring and pass one test suite (test/test_map_backends.py).

Modules: base (MapStore, MapCandidate), uri (backend_for), matcher_open (open_for_matcher), index
(GlobalIndex), sqlite (+ sqlite_file, sqlite_landmarks), milvus. A backend module is imported when a
URI first names it (BACKENDS), so the SQLite backend never imports pymilvus.
"""

from __future__ import annotations

import importlib

from ..errors import MapError
from .base import FORMAT, MapCandidate, MapStore
from .index import GlobalIndex
from .matcher_open import open_for_matcher, space_model, writable_problem
from .uri import backend_for

# backend name (backend_for) -> (module, class), imported on first use
BACKENDS = {
    'sqlite': ('lln_ros.mapstore.sqlite', 'SQLiteMapStore'),
    'milvus': ('lln_ros.mapstore.milvus', 'MilvusMapStore'),
}
_LAZY = {'SQLiteMapStore': 'sqlite', 'MilvusMapStore': 'milvus'}


def backend_class(kind: str) -> type:
    """The MapStore subclass of a backend name ('sqlite' | 'milvus')."""
    module, name = BACKENDS[kind]
    return getattr(importlib.import_module(module), name)


def open_map(
    uri, model: dict | None = None, create: bool = True, verify: bool = True, conf: dict | None = None
) -> MapStore:
    """The map at uri, in the backend the URI names (backend_for); same as MapStore.open."""
    return backend_class(backend_for(uri)[0])(uri, model=model, create=create, verify=verify, conf=conf)


def __getattr__(name):
    if name in _LAZY:
        return backend_class(_LAZY[name])
    if name in ('SCHEMA_VERSION', 'SCHEMA', 'MIGRATIONS', 'SQLITE_MAGIC'):
        from . import sqlite_file

        return getattr(sqlite_file, name)
    raise AttributeError(f'module {__name__!r} has no attribute {name!r}')


__all__ = [
    'BACKENDS',
    'FORMAT',
    'GlobalIndex',
    'MapCandidate',
    'MapError',
    'MapStore',
    'MilvusMapStore',
    'SQLiteMapStore',
    'SCHEMA_VERSION',
    'backend_class',
    'backend_for',
    'open_for_matcher',
    'open_map',
    'space_model',
    'writable_problem',
]

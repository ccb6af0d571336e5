"""Map URIs: which backend a map URI names."""

from __future__ import annotations

import os


def backend_for(uri) -> tuple[str, str]:
    """('sqlite' | 'milvus', location) for a map URI.

    plain path or sqlite:///path        the embedded backend (SQLite file + in-memory FAISS)
    milvus://host:port[/db][?map=name]  a Milvus server or cluster
    milvus-lite:///path.db              Milvus Lite, the embedded Milvus (a directory at path.db)
    an existing Milvus Lite directory   Milvus Lite (it holds LOCK, collections/, databases/)
    """
    text = os.fspath(uri)
    if text.startswith('sqlite://'):
        return 'sqlite', text[len('sqlite://') :]
    if text.startswith(('milvus://', 'milvus-lite:')):
        return 'milvus', text
    path = os.path.abspath(os.path.expanduser(text))
    if os.path.isdir(path) and os.path.isdir(os.path.join(path, 'collections')):
        return 'milvus', 'milvus-lite://' + path
    return 'sqlite', text

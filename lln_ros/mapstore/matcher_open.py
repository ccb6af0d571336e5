"""Opening a map the way the matcher does: the descriptor space validated, a map that mapping mode
cannot write refused before the file is touched, and the open's integrity scan reported."""

from __future__ import annotations

import os

from ..core.limits import validate_model
from ..errors import MapError
from .base import MapStore
from .uri import backend_for


def space_model(space: str) -> dict:
    """{'descriptor_space', 'descriptor_dim'} from a 'backbone/layer/D' string (validated)."""
    try:
        dim = int(space.rsplit('/', 1)[1])
    except (IndexError, ValueError):
        raise ValueError(f"descriptor_space must look like 'backbone/layer/D', got {space!r}") from None
    return validate_model({'descriptor_space': space, 'descriptor_dim': dim})


def writable_problem(uri) -> str:
    """Why the map at uri cannot be written ('' = it can, or it is not an SQLite file we can judge).
    Asked before the file is opened, so a refused map leaves no -wal/-shm behind."""
    kind, location = backend_for(uri)
    if kind != 'sqlite':
        return ''
    path = os.path.abspath(os.path.expanduser(os.fspath(location)))
    folder = os.path.dirname(path)
    if os.path.exists(path):
        if not os.access(path, os.W_OK):
            return f'map {path} is not writable (read-only file or file system)'
        if not os.access(folder, os.W_OK | os.X_OK):
            return (
                f'map {path}: its folder {folder} is not writable, and SQLite keeps the -wal and -shm '
                f'files of a map being written beside it'
            )
        return ''
    while folder and not os.path.exists(folder):
        folder = os.path.dirname(folder) if os.path.dirname(folder) != folder else ''
    if folder and os.path.isdir(folder) and not os.access(folder, os.W_OK | os.X_OK):
        return f'map {path} cannot be created: folder {folder} is not writable'
    return ''


def open_for_matcher(uri, mode: str = 'localization', descriptor_space: str = '', conf: dict | None = None):
    """(store, {quarantined keyframe id: problem}) for the matcher: the model from descriptor_space
    validated, a map that mapping mode cannot write refused (MapError naming the file and why),
    and the map's damaged keyframes found by the open's integrity scan."""
    model = space_model(descriptor_space) if descriptor_space else None
    if mode == 'mapping':
        problem = writable_problem(uri)
        if problem:
            raise MapError(
                f'{problem}; mode mapping needs to store keyframes (use mode localization, or fix the permissions)'
            )
    store = MapStore.open(uri, model=model, conf=conf)
    return store, store.quarantined

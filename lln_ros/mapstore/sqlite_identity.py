"""The SQLite map file's identity under a running store: a map deleted or replaced while a node holds
it open must be a loud error, never a silent success, and must lose nothing acknowledged.

SQLite keeps writing into an open file after it is unlinked: before this check (issue 25) a node went
on acknowledging keyframes into a deleted map, ~/save answered success, and the restart created an
empty map. Now every write (SQLiteMapStore._write: before BEGIN and after COMMIT), save() and close()
compare the path's (st_dev, st_ino) with the file opened:

    vanished   nothing at the path any more: the open connection is copied (SQLite's backup API, a
               consistent snapshot of everything committed, WAL included) to a temporary file that
               is linked into the path, and the store reconnects to it. The write that found it
               fails with MapError (counted by the caller: keyframes_failed / queries_failed,
               ~/save false); the next one goes to the restored file. Nothing acknowledged is lost,
               and a restart opens the restored map.
    replaced   another file at the path: it is not ours to overwrite. The open connection is copied
               to <path>.rescued-<time>.db, the store closes its connection, and every later call
               raises MapError naming both files (the node stays up; restart it, or move the rescued
               copy back).
"""

from __future__ import annotations

import logging
import os
import sqlite3
import time

from ..errors import MapError
from .sqlite_file import fsync_path

log = logging.getLogger(__name__)


def _inode(path: str) -> tuple | None:
    try:
        st = os.stat(path)
    except FileNotFoundError:
        return None
    return (st.st_dev, st.st_ino)


class SQLiteIdentity:
    """Mixin of SQLiteMapStore (uses path, _conn, _configure, _data_version, _ids)."""

    _identity: tuple | None = None
    _lost: str = ''  # set when the file was replaced: every later call raises MapError(_lost)

    def _file_identity(self) -> tuple | None:
        return _inode(self.path)

    def _remember_identity(self) -> None:
        self._identity = self._file_identity()

    def _check_identity(self, when: str) -> None:
        """MapError (after restoring or rescuing what this store holds) when the file at the path is
        not the one opened."""
        if self._lost:
            raise MapError(self._lost)
        now = self._file_identity()
        if now == self._identity or self._conn is None:
            return
        held = len(self._ids)
        if now is None:
            self._restore_in_place()
            text = (
                f'map {self.path} was deleted while this node had it open (found {when}); its {held} '
                f'keyframes were restored to {self.path} from the open connection; this call failed, '
                f'the next write goes to the restored file'
            )
            log.error('%s', text)
            raise MapError(text)
        rescued = self._rescue_copy(f'{self.path}.rescued-{time.strftime("%Y%m%dT%H%M%S")}-{os.getpid()}.db')
        self._lost = (
            f'map {self.path} was replaced by another file while this node had it open (found {when}); '
            f'the {held} keyframes this node held were saved to {rescued}; this map is refused from now '
            f'on: restart the node to open the new file, or move the rescued copy back'
        )
        # our -wal/-shm are still named after the path: SQLite does not checkpoint into a moved
        # file, and a leftover WAL would be replayed into the replacement when it is next opened
        # (seen: the replacement gained our keyframes). Ours are the ones we held: same inode
        ours = {suffix: _inode(self.path + suffix) for suffix in ('-wal', '-shm')}
        conn, self._conn = self._conn, None
        conn.close()
        for suffix, inode in ours.items():
            if inode is not None and _inode(self.path + suffix) == inode:
                os.remove(self.path + suffix)
        log.error('%s', self._lost)
        raise MapError(self._lost)

    def _rescue_copy(self, target: str) -> str:
        """A consistent copy of everything committed on the open connection, as a self-contained
        file at target (no -wal beside it). MapError when even that fails."""
        try:
            dest = sqlite3.connect(target, isolation_level=None)
            try:
                self._conn.backup(dest)
                dest.execute('PRAGMA journal_mode=DELETE')  # one file: nothing left in a -wal
            finally:
                dest.close()
            fsync_path(target)
        except (OSError, sqlite3.Error) as e:
            raise MapError(
                f'map {self.path} changed under this node and its open copy could not be saved to {target}: {e}'
            ) from e
        return target

    def _restore_in_place(self) -> None:
        """The path is empty: put the open connection's content back there and reconnect to it."""
        try:
            os.makedirs(os.path.dirname(self.path), exist_ok=True)  # rm -r of the folder, too
        except OSError as e:
            raise MapError(f'map {self.path} was deleted under this node and its folder cannot be made again: {e}')
        tmp = self._rescue_copy(f'{self.path}.restoring-{os.getpid()}')
        # our WAL and shared-memory files are still named <path>-wal/-shm: closing the old
        # connection checkpoints into the unlinked file and removes them, so the restored file
        # can never meet a WAL that is not its own
        self._conn.close()
        self._conn = None
        for suffix in ('-wal', '-shm'):
            try:
                os.remove(self.path + suffix)
            except FileNotFoundError:
                pass
        try:
            os.link(tmp, self.path)  # fails if a file appeared meanwhile: never overwrite it
            os.remove(tmp)
        except OSError as e:
            self._lost = f'map {self.path} was deleted under this node; its content is saved in {tmp} ({e})'
            raise MapError(self._lost) from e
        self._conn = sqlite3.connect(self.path, timeout=10.0, isolation_level=None, check_same_thread=False)
        self._configure()
        self._data_version = None  # the next call reloads the index from the restored file
        self._remember_identity()

"""Keyframe identity in a shared map (issue 29): which robot, in which session, stored a keyframe.

    s = store.start_session('robot1')                 # Session(id, robot, label, started_ns)
    store.set_origin(keyframe_id, s.id, seq)          # seq: the keyframe's number in its session, from 1
    store.origins([ids]) -> {keyframe_id: Origin}     # keyframes of before schema 3 have none
    store.sessions() -> [Session]
    log = SessionLog(store, 'robot1')                 # what a mapping matcher keeps: the session, its seq

A keyframe's identity is (robot, session label, seq): it survives a merge into another map, where
the keyframe gets a new map-wide keyframe_id and its session a new map-wide number (Session.id,
what the answers carry as `session_id`). A label is the session's UTC start time with a random
suffix, so two runs of one robot, or two robots given the same robot_id, never share a session.
"""

from __future__ import annotations

import hashlib
import re
import secrets
import threading
import time
from dataclasses import dataclass

import numpy as np

ROBOT_ID_MAX = 64
_ROBOT_ID = re.compile(r'[A-Za-z0-9_][A-Za-z0-9_./-]*\Z')


@dataclass(frozen=True)
class Session:
    """One run of one robot writing into a map. id: the map's number for it (>= 1)."""

    id: int
    robot: str
    label: str
    started_ns: int


@dataclass(frozen=True)
class Origin:
    """Where a keyframe came from: its session (the map's number) and its number in it (>= 1)."""

    session_id: int
    seq: int


def check_robot_id(robot) -> str:
    """The robot id, or ValueError: 1-64 characters of letters, digits and _ . / - (a ROS namespace
    or host name fits), not starting with . / -."""
    if not isinstance(robot, str) or not 0 < len(robot) <= ROBOT_ID_MAX or not _ROBOT_ID.match(robot):
        raise ValueError(
            f'robot id must be 1-{ROBOT_ID_MAX} characters of letters, digits, _ . / - (not first), got {robot!r}'
        )
    return robot


def check_label(label) -> str:
    if not isinstance(label, str) or not 0 < len(label) <= 64 or not _ROBOT_ID.match(label):
        raise ValueError(f'session label must be 1-64 characters of letters, digits, _ . / -, got {label!r}')
    return label


def new_label(now_ns: int | None = None) -> str:
    """A session label: its UTC start time and 6 random hex digits (20261203T131500Z-3fa2c1)."""
    now_ns = time.time_ns() if now_ns is None else int(now_ns)
    return time.strftime('%Y%m%dT%H%M%SZ', time.gmtime(now_ns // 10**9)) + '-' + secrets.token_hex(3)


def robot_from_namespace(namespace: str, hostname: str) -> str:
    """The default robot id: the node's namespace without slashes at its ends (/fleet/robot1 ->
    fleet/robot1), or the host name when the node runs in the root namespace."""
    name = namespace.strip('/')
    return name if name else re.sub(r'[^A-Za-z0-9_.-]', '_', hostname)[:ROBOT_ID_MAX] or 'robot'


def content_digest(lset, stamp) -> str:
    """A digest of what a keyframe is (stamp, grid, global descriptor, cells, landmark descriptors):
    the same keyframe read from two maps has the same digest (lln-map merge keeps it once)."""
    h = hashlib.sha1()
    h.update(np.asarray([int(stamp[0]), int(stamp[1]), *(int(v) for v in lset.grid)], '<i8').tobytes())
    h.update(np.ascontiguousarray(lset.global_descriptor, '<f4').tobytes())
    h.update(np.ascontiguousarray(lset.cells, '<i2').tobytes())
    h.update(np.ascontiguousarray(lset.descriptors, '<f2').tobytes())
    return h.hexdigest()


class SessionLog:
    """A mapping matcher's session: started in the store at construction (and by new()), numbering
    the keyframes it stores. count: keyframes stored in this session (the recent-keyframe exclusion
    applies to them only: another robot's or an earlier session's keyframe is a valid answer);
    ids: theirs, in the order stored (in a map several processes write they need not be the
    map's highest ids, so the exclusion names them)."""

    def __init__(self, store, robot: str):
        self.store, self.robot = store, check_robot_id(robot)
        self._lock = threading.Lock()
        self.new()

    def new(self) -> Session:
        with self._lock:
            self.session = self.store.start_session(self.robot)
            self.count, self.ids = 0, []
            return self.session

    def stored(self, keyframe_id: int) -> Origin:
        with self._lock:
            self.count += 1
            self.ids.append(int(keyframe_id))
            origin = Origin(self.session.id, self.count)
        self.store.set_origin(keyframe_id, origin.session_id, origin.seq)
        return origin

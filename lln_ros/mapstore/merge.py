"""Copying keyframes between maps with everything they carry: landmarks, stamp, geometry, verify
keypoints, and their identity (sessions.py). Either backend on either side.

    report = merge_into(dst, src)                 # new ids in dst; a keyframe dst has already is skipped
    report = merge_into(dst, src, keep_ids=True)  # the ids kept (lln-map export / import); taken ids refused

merge_into is what `lln-map merge A B DEST` runs once per source. A keyframe's identity in the
destination is its content (sessions.content_digest: stamp, grid and descriptors), so merging a map
with itself, or with a copy of a map it already holds, adds nothing; its session comes along by
(robot, label), so its (robot, session, seq) is the same in both maps. A keyframe of a map from
before schema 3 (no origin) is given one: robot `legacy_robot` (default: the source map's file name),
a session named after the source map, seq = its old id.
"""

from __future__ import annotations

import hashlib
import os
import re
from dataclasses import dataclass, field

from ..errors import MapError
from .sessions import ROBOT_ID_MAX, Origin, content_digest

BATCH = 256  # keyframes per add_many (one SQLite transaction)


@dataclass
class MergeReport:
    """read: keyframes of the source; added: stored in the destination (new ids); present: skipped,
    the destination holds them already; sessions: the destination's session ids they belong to;
    ids: {source id: destination id} of every keyframe read."""

    read: int = 0
    added: int = 0
    present: int = 0
    sessions: set = field(default_factory=set)
    ids: dict = field(default_factory=dict)


def digests(store) -> dict[str, int]:
    """{content digest: keyframe id} of every keyframe of a map."""
    return {content_digest(lset, stamp): kid for kid, stamp, lset in store.keyframes(BATCH)}


def legacy_robot_name(store) -> str:
    base = os.path.splitext(os.path.basename(str(store.path).rstrip('/')))[0] or 'map'
    return re.sub(r'[^A-Za-z0-9_.-]', '_', base).lstrip('.-')[:ROBOT_ID_MAX] or 'map'


def merge_into(
    dst, src, keep_ids: bool = False, legacy_robot: str | None = None, known: dict | None = None
) -> MergeReport:
    """Copy every keyframe of src into dst (module doc). known: digests(dst), when the caller has it
    (merging several sources: computed once, updated here). MapError when the models differ or,
    with keep_ids, an id is taken by another keyframe."""
    if src.model is None:
        raise MapError(f'map {src.path} has no model record (never used); nothing to copy')
    if dst.model is None:
        dst.use_model(src.model)
    elif not dst._same_space(src.model):
        raise dst._mismatch(src.model, f'the keyframes of map {src.path}')
    known = digests(dst) if known is None else known
    sessions = _sessions_in(dst, src, legacy_robot)
    origins = src.origins()
    report, batch = MergeReport(), []
    for kid, stamp, lset in src.keyframes(BATCH):
        report.read += 1
        digest = content_digest(lset, stamp)
        if digest in known:
            report.present += 1
            report.ids[kid] = known[digest]
            continue
        batch.append((kid, stamp, lset, digest))
        if len(batch) == BATCH:
            _flush(dst, src, batch, keep_ids, origins, sessions, known, report)
    _flush(dst, src, batch, keep_ids, origins, sessions, known, report)
    dst.save()
    return report


def _sessions_in(dst, src, legacy_robot: str | None) -> dict:
    """{source session id (0: keyframes without one): the destination's Session}."""
    out = {s.id: dst.start_session(s.robot, s.label, s.started_ns) for s in src.sessions()}
    label = 'legacy-' + hashlib.sha1(str(src.path).encode()).hexdigest()[:12]
    out[0] = (legacy_robot or legacy_robot_name(src), label)  # started only when a keyframe needs it
    return out


def _flush(dst, src, batch: list, keep_ids: bool, origins: dict, sessions: dict, known: dict, report) -> None:
    if not batch:
        return
    ids = dst.add_many([b[2] for b in batch], [b[1] for b in batch], ids=[b[0] for b in batch] if keep_ids else None)
    has_kps = hasattr(src, 'keypoints') and hasattr(dst, 'add_keypoints')
    for (old, _, _, digest), new in zip(batch, ids):
        origin = origins.get(old) or Origin(0, int(old))
        if isinstance(sessions.get(origin.session_id), tuple):  # the legacy session, started on first use
            sessions[origin.session_id] = dst.start_session(*sessions[origin.session_id])
        session = sessions.get(origin.session_id)
        if session is None:
            raise MapError(f'map {src.path}: keyframe {old} names session {origin.session_id}, which the map lacks')
        dst.set_origin(new, session.id, origin.seq)
        kps = src.keypoints(old) if has_kps else None
        if kps is not None:
            dst.add_keypoints(new, *kps)
        geom = src.geometry(old) if hasattr(src, 'geometry') else None
        if geom is not None:  # after the keypoints: its depths are aligned with them
            dst.set_geometry(new, geom)
        known[digest] = new
        report.ids[old] = new
        report.sessions.add(session.id)
    report.added += len(ids)
    batch.clear()

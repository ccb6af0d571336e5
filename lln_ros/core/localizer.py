"""The matcher's decisions, without rclpy: what happens to each model_info, keyframe, query and
keypoints message once the node has decoded it.

    store, quarantined = mapstore.open_for_matcher(uri, mode='mapping')   # FATAL-worthy errors raise
    loc = Localizer(store, conf, counters)          # counters: lln_ros.core.counters.Counters (node: Health)
    loc.model_info(text)                            # the extractor's latched JSON
    args = loc.landmark_decoding('bad_query')       # kwargs for msgs.cloud_to_landmarks, None = refusing
    loc.keyframe(lset, stamp_ns)                    # -> keyframe id or None (refused / failed, counted)
    if loc.query_fresh(stamp_ns, now_ns):
        answer = loc.query(lset, stamp_ns)          # -> Answer(rows, extra_fields, best) or None
    loc.keypoints(payload, stamp_ns)                # verify: paired with its landmark set by stamp

Every refusal is counted under one counter and logged by kind (Counters.problem); nothing a message
declares is used to size an allocation before lln_ros.core.limits has checked it. Counters (documented in
docs/interfaces.md §3.6) keep these sums for every input:

    queries_received                  = queries_answered + queries_stale + bad_query + queries_failed
    keyframes_received + queries_stored = keyframes_stored + bad_keyframe + keyframes_failed

(queries_stored: mapping mode's queries stored as keyframes; those the keyframe gate refuses are
queries_not_stored. The metric side, camera, odometry, poses and gating, is core.registration's: loc.reg.)
*_failed: the map, not the message, was at fault (a keyframe damaged after start, a write that
failed, or an internal error): the message is not blamed as bad_*.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

from ..errors import DescriptorError, LLNError, MapError
from . import limits as limits_mod
from . import registration as registration_mod
from . import sequence as sequence_mod
from .landmark_index import check_prefilter
from .limits import LimitError, check_landmark_set, height_change, parse_model_json, stamp_problem, validate_model
from .pending import Pending, keep_newest
from .retrieval import candidates_k
from .retrieval import default_conf as retrieval_conf
from .similarity import CENTERS, DEFAULT_SIMILARITY
from .threads import one_thread

default_conf = {
    'mode': 'localization',  # localization: answer queries only | mapping: answer, then store each query
    'prefilter': retrieval_conf['prefilter'],  # first stage: landmarks | holistic | exhaustive
    'prefilter_k': retrieval_conf['prefilter_k'],  # first-stage candidates reranked by S; 0 = every keyframe
    # with sequence_length > 0: max(prefilter_k, this) candidates (retrieval.candidates_k); 0 = every keyframe
    'sequence_prefilter_k': retrieval_conf['sequence_prefilter_k'],
    'k': 5,  # candidates answered per query
    'min_score': 0.0,  # candidates below this are not answered
    'exclude_recent': 10,  # mapping mode: the newest N keyframes are never answers
    'method': 'lln',  # lln: rerank by landmark similarity S | holistic: global descriptor only
    'similarity': DEFAULT_SIMILARITY,  # S's sets: raw | center | whiten | fuse (similarity.CENTERS; docs/method.md)
    'offset_scale': 1.0,  # Gaussian width of the offset weights, grid cells
    'max_query_age': 0.0,  # seconds; older queries are dropped (queries_stale); 0 = off
    'verify': False,  # re-rank candidates by keypoint inliers
    'verify_min_inliers': 15,
    'verify_margin': 1.0,
    'sequence_length': 0,  # 0 = single-frame ranking
    'sequence_max_gap': 1.0,
    # with sequence_length: the best N sequence ends' next places (KeyframeSequence.ahead) are reranked too
    'sequence_carry': retrieval_conf['sequence_carry'],
    'sequence_acquire_k': retrieval_conf['sequence_acquire_k'],  # candidates while the window fills; 0 = off
    'sequence_score_norm': sequence_mod.default_conf['score_norm'],  # each query's S before the line search
    # verify: bytes of keypoints messages waiting for their landmark set (the oldest are evicted, as
    # keypoints_evicted): 100 of 500 keypoints are 2.8 MB; 100 declaring 1 row, 8 MB each were 816 MB
    'pending_keypoints_bytes': 16 * 2**20,
    'limits': limits_mod.default_conf,
    # the metric side (camera, depth, odometry, poses, gating): lln_ros.core.registration.default_conf
    'registration': registration_mod.default_conf,
}
CHOICES = {'mode': ('localization', 'mapping'), 'method': ('lln', 'holistic'), 'similarity': tuple(CENTERS)}
CHOICES['sequence_score_norm'] = sequence_mod.SCORE_NORMS
PENDING = 100  # keypoints messages / keyframes waiting for their partner (by stamp), newest kept
KEYPOINT_ROW_BYTES = 56  # one keypoints cloud row (msgs.KEYPOINT_FIELDS: 5 float32, int32, 32 uint8)


@dataclass
class Answer:
    """One query's answer. rows: candidate rows for msgs.candidates_to_cloud (best first);
    extra_fields: the optional FLOAT32 fields every answer of this node carries; best: the
    MapCandidate whose matched regions go on the matches topic (None: no candidate)."""

    rows: list
    extra_fields: tuple
    best: object = None
    inliers: dict = field(default_factory=dict)
    pose: object = None  # core.registration.PoseAnswer of the best candidate, or None


class Localizer:
    """Per-message logic of the matcher (see the module docstring). Thread-compatible with one
    caller at a time (the node's single-threaded executor); the store is thread-safe itself."""

    def __init__(self, store, conf: dict | None = None, counters=None, log=None, decode_keypoints=None):
        from .counters import Counters

        self.conf = conf = self.check_conf(conf)
        self.store, self.limits = store, conf['limits']
        self.log = log or logging.getLogger('lln_ros.core.localizer')
        self.counters = counters if counters is not None else Counters(log=self.log.warning)
        self.mapping = conf['mode'] == 'mapping'
        self.reg = registration_mod.Registration(conf['registration'], self.counters)
        self.sequence = sequence_mod.KeyframeSequence.of(conf)
        self.refusing = ''  # set when the extractor's model differs from the map's
        self.extractor_model = None  # the last valid model_info: its input_height fixes the grid rows
        self.reloc, self.unmatched_keyframes = None, {}
        self.session = None  # a mapping matcher's mapstore.sessions.SessionLog: numbers its keyframes
        self.pending_keypoints = Pending(PENDING, conf['pending_keypoints_bytes'])
        # decode_keypoints(payload, image_size (w, h), scale, max_rows) -> reloc.Keypoints
        self.decode_keypoints = decode_keypoints or (lambda kps, *_: kps)
        if conf['verify']:
            if not hasattr(store, 'add_keypoints'):
                raise MapError(
                    f'verify needs keypoint storage, which the {type(store).__name__} backend of '
                    f'map {store.path} does not have (use an SQLite map)'
                )
            from .reloc import Relocalizer

            self.reloc = Relocalizer({'min_inliers': conf['verify_min_inliers'], 'margin': conf['verify_margin']})

    @staticmethod
    def check_conf(conf: dict | None) -> dict:
        """default_conf updated by conf, checked (ValueError naming the bad value)."""
        conf = dict(conf or {})
        conf = {**default_conf, **conf, 'limits': limits_mod.limits(conf.get('limits'))}
        conf['registration'] = {**registration_mod.default_conf, **(conf.get('registration') or {})}
        registration_mod.check_conf(conf['registration'])
        for key, choices in CHOICES.items():
            if conf[key] not in choices:
                raise ValueError(f'{key} must be one of {choices}, got {conf[key]!r}')
        if conf['prefilter_k'] < 0:
            raise ValueError(f'prefilter_k must be 0 (every keyframe) or positive, got {conf["prefilter_k"]}')
        check_prefilter(conf['prefilter'], conf['prefilter_k'])
        candidates_k(conf['prefilter_k'], conf['sequence_prefilter_k'], True)  # ValueError when negative
        for key in ('sequence_length', 'sequence_carry', 'sequence_acquire_k'):
            if conf[key] < 0:
                raise ValueError(f'{key} must be 0 (off) or positive, got {conf[key]}')
        return conf

    def count(self, key: str, n: int = 1) -> None:
        self.counters.count(key, n)

    # ------------------------------------------------------------------ model

    def model_info(self, text: str) -> None:
        """The extractor's model (JSON). Validated completely first (limits.validate_model): a bad
        one is counted as bad_model_info and changes nothing, neither the map nor the refusal state.
        A valid one is declared to the map: recorded on a new map, or the refusal is set/lifted."""
        self.count('model_info_received')
        try:
            # bounded in size and depth before it is parsed (limits.parse_model_json): nothing
            # recorded in the map can fail to be written or read back
            model = validate_model(parse_model_json(text), self.limits)
        except (ValueError, RecursionError) as e:  # JSONDecodeError and ModelError are ValueErrors
            self.counters.problem('bad_model_info', f'cannot use model_info: {e}')
            return
        said = height_change(self.extractor_model or self.store.model or {}, model)
        if said:
            self.log.error(said)
        self.extractor_model = model
        try:
            self.store.use_model(model)
            self.refusing = ''
        except MapError as e:
            if str(e) != self.refusing:
                self.log.error(f'{e}; landmark input is refused until the models agree')
            self.refusing = str(e)

    def landmark_decoding(self, counter: str) -> dict | None:
        """kwargs for msgs.cloud_to_landmarks (expected_dim, descriptor_space, limits), or None when
        landmark input is refused (model conflict; counted under `counter`)."""
        if self.refusing:
            self.counters.problem(counter, self.refusing)
            return None
        model = self.store.model or {}
        space, dim = model.get('descriptor_space', ''), model.get('descriptor_dim')
        return {'expected_dim': dim, 'descriptor_space': space, 'limits': self.limits}

    def refuse(self, counter: str, error: Exception) -> None:
        """Count and log (by kind) a message the node could not decode."""
        self.counters.problem(counter, str(error))

    def check(self, lset) -> None:
        """Everything about a decoded landmark set that the store and the similarity rely on, so a
        later failure is the map's, not the message's (LLNError naming the problem)."""
        lset.validate()
        if len(lset) == 0:
            raise DescriptorError('landmark set has no landmarks')
        check_landmark_set(lset, self.extractor_model, self.limits)

    # ------------------------------------------------------------------ keyframes and keypoints

    def keyframe(self, lset, stamp_ns: int) -> int | None:
        """Store a decoded keyframe (with its keypoints when they came first); its id, or None.
        The caller counts keyframes_received for every keyframes message, decodable or not."""
        try:
            self.check(lset)
            if self.store.model is None and not lset.descriptor_space:
                raise MapError(
                    f'landmark set has no descriptor_space; refusing to store it in map {self.store.path} '
                    f'(a persistent map must know which model made its descriptors: set the '
                    f'descriptor_space parameter or run the extractor, which publishes model_info)'
                )
        except LLNError as e:
            self.counters.problem('bad_keyframe', str(e))
            return None
        try:
            odom = self.reg.odometry_at(stamp_ns)
            return self._store_keyframe(lset, stamp_ns, self._take_keypoints(stamp_ns, lset), odom)
        except MapError as e:
            self._failed('keyframes_failed', e)
        except (LLNError, ValueError) as e:  # the store's own checks (e.g. no model recorded yet)
            self.counters.problem('bad_keyframe', str(e))
        except Exception as e:  # noqa: BLE001  one message never ends the node
            self._failed('keyframes_failed', e)
        return None

    def keypoints(self, payload, stamp_ns: int, nbytes: int = 0) -> None:
        """Keypoints are held until the landmark set with the same stamp arrives (the newest 100, at
        most pending_keypoints_bytes in all, are kept); two topics are not ordered, so keypoints of a
        keyframe already stored are attached. nbytes: the payload's size (the node's len(msg.data));
        a message larger than max_keypoints rows can be is refused (bad_keypoints) before it is kept."""
        most = self.limits['max_keypoints'] * KEYPOINT_ROW_BYTES
        if nbytes > most:
            self.counters.problem(
                'bad_keypoints',
                f'keypoints cloud: {nbytes} bytes is more than max_keypoints {self.limits["max_keypoints"]} '
                f'rows of {KEYPOINT_ROW_BYTES} bytes ({most}); not kept',
            )
            return
        kid = self.unmatched_keyframes.pop(stamp_ns, None)
        if kid is None:
            if self.pending_keypoints.put(stamp_ns, payload, nbytes):
                self.counters.problem(
                    'keypoints_evicted',
                    f'verify: keypoints waiting for their landmark set exceed {PENDING} messages or '
                    f'pending_keypoints_bytes {self.conf["pending_keypoints_bytes"]}; the oldest dropped',
                    kind='evicted',
                )
            return
        try:
            kps = self._decode_keypoints(payload, self.store.get(kid))
            if kps is not None:
                self.store.add_keypoints(kid, kps.uv, kps.descriptors)
                if kps.depth is not None:
                    self.store.set_geometry(kid, {'depth': kps.depth})
        except (LLNError, KeyError) as e:
            self.counters.problem('bad_keypoints', str(e))

    def _take_keypoints(self, stamp_ns: int, lset):
        """The keypoints sent with this landmark set (by stamp), decoded, or None."""
        payload = self.pending_keypoints.take(stamp_ns) if self.reloc else None
        if payload is None:
            if self.reloc:
                self.count('verify_missing_keypoints')
            return None
        return self._decode_keypoints(payload, lset)

    def _decode_keypoints(self, payload, lset):
        from .reloc import detection_scale

        w, h = (float(v) for v in lset.image_size)
        try:
            return self.decode_keypoints(
                payload, (w, h), detection_scale(h, self.reloc.conf['min_height']), self.limits['max_keypoints']
            )
        except LLNError as e:
            self.counters.problem('bad_keypoints', str(e))
            return None

    def _store_keyframe(self, lset, stamp_ns: int, kps, odom=None) -> int:
        kid = self.store.add(lset, divmod(int(stamp_ns), 1_000_000_000))
        if self.session is not None:
            self.session.stored(kid)
        geom = self.reg.keyframe_geometry(lset.image_size, odom)  # checked again by the store: no broken pose
        if geom['camera'] is not None or geom['pose'] is not None:
            self.store.set_geometry(kid, geom)
        self.reg.stored(stamp_ns, odom, lset)
        if kps is not None:
            self.store.add_keypoints(kid, kps.uv, kps.descriptors)
            if kps.depth is not None:
                self.store.set_geometry(kid, {'depth': kps.depth})
        elif self.reloc is not None:  # its keypoints may still come
            self.unmatched_keyframes[stamp_ns] = kid
            keep_newest(self.unmatched_keyframes, PENDING)
        self.count('keyframes_stored')
        return kid

    def _stored_keypoints(self, keyframe_id: int, image_size):
        from .reloc import Keypoints, detection_scale

        found = self.store.keypoints(keyframe_id)
        if found is None:
            return None
        uv, desc = found
        kps = Keypoints.empty(image_size)
        kps.uv, kps.descriptors = uv, desc
        kps.scale = detection_scale(image_size[1], self.reloc.conf['min_height'])
        geom = self.store.geometry(keyframe_id) if self.geometry else None
        if geom is not None and geom['depth'] is not None and len(geom['depth']) == len(uv):
            kps.depth = geom['depth']
        return kps

    def _failed(self, counter: str, error: Exception) -> None:
        what = str(error) if isinstance(error, LLNError) else f'internal error {type(error).__name__}: {error}'
        self.counters.problem(counter, what, kind=None if isinstance(error, LLNError) else type(error).__name__)

    # ------------------------------------------------------------------ queries

    def query_fresh(self, stamp_ns: int, now_ns: int) -> bool:
        """Count a received query; False (counted as queries_stale) when its stamp is more than
        max_query_age from the node's clock either way: older, or ahead (a future stamp is no
        fresher than an old one; those are counted as queries_future too)."""
        self.count('queries_received')
        max_age = self.conf['max_query_age']
        age = (now_ns - stamp_ns) * 1e-9
        if max_age > 0 and abs(age) > max_age:
            self.count('queries_stale')
            if age < 0:
                self.counters.problem(
                    'queries_future',
                    f"query stamped {-age:.3f} s ahead of this node's clock, more than max_query_age "
                    f'{max_age:g} s: dropped as stale (clocks apart? use_sim_time on one node only?)',
                )
            return False
        return True

    def query(self, lset, stamp_ns: int) -> Answer | None:
        """Answer a decoded query (after query_fresh); in mapping mode it is stored before the answer
        is returned (an answered keyframe is never lost). None: refused or failed (counted)."""
        try:
            self.check(lset)
        except LLNError as e:
            self.counters.problem('bad_query', str(e))
            return None
        try:
            with one_thread():  # one query's arithmetic is too small to split (core.threads)
                return self._answer(lset, stamp_ns)
        except Exception as e:  # noqa: BLE001  MapError: the map's fault; anything else: ours
            self._failed('queries_failed', e)
            return None

    def _answer(self, lset, stamp_ns: int) -> Answer:
        c = self.conf
        kps = self._take_keypoints(stamp_ns, lset)
        odom = self.reg.odometry_at(stamp_ns)
        sequence = self.sequence is not None  # the sequence search needs every reranked candidate
        prefilter_k = candidates_k(c['prefilter_k'], c['sequence_prefilter_k'], sequence)
        if sequence and prefilter_k and c['sequence_acquire_k'] and self.sequence.matcher.filling(stamp_ns):
            prefilter_k = max(prefilter_k, int(c['sequence_acquire_k']))  # too few frames to outvote a wrong line
        recent = self._own(max(c['exclude_recent'], self.reg.recent(stamp_ns, odom))) if self.mapping else 0
        carried = self.sequence.ahead() if sequence and c['sequence_carry'] else ()
        found = self.store.query(
            lset,
            prefilter=c['prefilter'],
            prefilter_k=prefilter_k,
            include_ids=carried,
            k=(prefilter_k or max(len(self.store), 1)) + len(carried) if sequence else c['k'],
            min_score=None if sequence else c['min_score'],
            method_rerank=c['method'] == 'lln',
            scale=c['offset_scale'],
            center=CENTERS[c['similarity']],
            **self._recent(recent),
        )
        inliers, results, stored = {}, {}, False
        if self.reloc is not None:
            found, inliers, results = self.verify(lset, kps, found)
        pose = None
        if found and self.geometry:  # the best candidate's T(keyframe <- query), judged (core.registration)
            best, kid = found[0], found[0].keyframe_id
            kf_kps = self._stored_keypoints(kid, best.image_size) if kid in results else None
            kf_geom = self.store.geometry(kid) if kf_kps is not None else None
            pose = self.reg.pose_of(kps, kf_kps, results.get(kid), kf_geom, best, odom, lset.image_size)
        if self.mapping:  # committed before the answer goes out: an answered keyframe is never lost
            best = registration_mod.best_raw_score(found)  # the gate's threshold is in raw S
            stored = self.reg.gate(stamp_ns, odom, best, lset, c['offset_scale'])
            if stored:
                self._store_keyframe(lset, stamp_ns, kps, odom)
                self.count('queries_stored')
            else:  # the gate (odometry motion, or novelty) says it is not a new keyframe
                self.count('queries_not_stored')
        found = [m for m in found if self._stamp_ok(m.keyframe_id, m.stamp)]
        rows = [
            {
                'keyframe_id': m.keyframe_id,
                'score': m.score,
                'holistic_score': m.holistic_score,
                'stamp_sec': m.stamp[0],
                'stamp_nanosec': m.stamp[1],
                'session_id': float(m.session_id),
                **({'inliers': inliers.get(m.keyframe_id, float('nan'))} if self.reloc else {}),
            }
            for m in found
        ]
        if sequence:
            rows, found = self.sequence_rows(found, stamp_ns, inliers if self.reloc else None, stored)
        if self.geometry:  # the pose fields: on the row of the keyframe the pose is about, NaN elsewhere
            for row in rows:
                mine = pose is not None and row['keyframe_id'] == pose.keyframe_id
                row.update(pose.fields() if mine else registration_mod.nan_fields())
        extra = ('session_id',) + ('inliers',) * (self.reloc is not None) + ('sequence_score',) * sequence
        extra += registration_mod.POSE_FIELDS * self.geometry  # a zero-row answer carries them too
        return Answer(rows, extra, found[0] if found else None, inliers, pose)

    def _own(self, n: int, stored_now: int = 0) -> int:
        """The n newest keyframes are excluded only when this session stored them (issue 29): another
        robot's, or an earlier run's, is a valid answer. stored_now: the query's own keyframe is in."""
        return n if self.session is None else max(0, min(n, self.session.count - stored_now))

    def _recent(self, n: int) -> dict:
        """The query's exclusion of this session's n newest keyframes: by their ids (in a map that other
        processes write they need not be the highest), or the n highest ids without a session."""
        if self.session is None:
            return {'exclude_recent': n}
        return {'exclude_ids': self.session.ids[-n:] if n else ()}

    @property
    def geometry(self) -> bool:
        """Poses are estimated (and their fields answered): verify mode with registration's geometry on."""
        return self.reloc is not None and bool(self.reg.conf['geometry'])

    def _stamp_ok(self, keyframe_id: int, stamp) -> bool:
        """Whether a stored keyframe fits the answer's keyframe_id (UINT32), stamp_sec (INT32) and
        stamp_nanosec (< 1e9). One stored out of range by an older version (SQLite quarantines bad
        stamps at open; this covers any backend) is left out of the answer, counted as
        bad_stored_stamp, and never fails the encoder."""
        problem = stamp_problem(*stamp)
        if not 0 <= int(keyframe_id) <= limits_mod.KEYFRAME_ID_MAX:
            problem = f"id does not fit the answers' keyframe_id (UINT32, at most {limits_mod.KEYFRAME_ID_MAX})"
        if problem:
            self.counters.problem('bad_stored_stamp', f'map keyframe {keyframe_id}: {problem}; not answered')
        return not problem

    def verify(self, lset, kps, found):
        """Candidates re-ranked by region-constrained inliers, {keyframe_id: inliers} and
        {keyframe_id: reloc.RelocResult} (its matches: what the pose is estimated from)."""
        from .reloc import verify_candidates

        if kps is None or not found:
            return found, {}, {}
        ranked = verify_candidates(
            self.reloc, kps, lset.cell_size, found, lambda m: self._stored_keypoints(m.keyframe_id, m.image_size)
        )
        self.count('queries_verified')
        results = {m.keyframe_id: r for m, r in ranked if r is not None}
        return [m for m, _ in ranked], {kid: float(r.inliers) for kid, r in results.items()}, results

    def _sequence_excluded(self, stored: bool):
        """Ids the sequence search may not answer (mapping mode): the query's own keyframe, when stored,
        and this session's exclude_recent newest before it; another session's are answers."""
        n = self._own(self.conf['exclude_recent'], stored_now=int(stored)) + int(stored) if self.mapping else 0
        own = self.session.ids if self.session is not None else sorted(self.sequence.ids.tolist())
        return own[-n:] if n else None

    def sequence_rows(self, found: list, stamp_ns: int, inliers: dict | None = None, stored: bool = False):
        """Rows ranked by sequence_score, and the MapCandidates among them (same order) for matches.
        stored: the query's own keyframe was just stored. inliers: verify mode's {keyframe_id: inliers}."""
        self.sequence.follow(self.store)
        found_scores = {m.keyframe_id: m.score for m in found}
        excluded, c = self._sequence_excluded(stored), self.conf
        reason, ranked = self.sequence.update(stamp_ns, found_scores, excluded, c['k'], c['sequence_carry'])
        if reason:
            self.count(f'sequence_reset_{reason}')
        by_id = {m.keyframe_id: m for m in found}
        rows = []
        for kf, seq_score in ranked:
            if seq_score < self.conf['min_score']:
                continue
            m = by_id.get(kf)
            stamp = m.stamp if m else self.store.get(kf).meta['stamp']
            if m is None and not self._stamp_ok(kf, stamp):
                continue
            rows.append(
                {
                    'keyframe_id': kf,
                    'score': m.score if m else 0.0,
                    'holistic_score': m.holistic_score if m else 0.0,
                    'stamp_sec': stamp[0],
                    'stamp_nanosec': stamp[1],
                    'sequence_score': seq_score,
                    'session_id': float(
                        m.session_id if m else getattr(self.store.origins([kf]).get(kf), 'session_id', 0)
                    ),
                    **({'inliers': inliers.get(kf, float('nan'))} if inliers is not None else {}),
                }
            )
        first = by_id.get(rows[0]['keyframe_id']) if rows else None
        return rows, [first] if first else []

    def clear(self) -> int:
        """Remove every keyframe (~/clear); the sequence search forgets the map too."""
        removed = self.store.clear()
        self.reg.forget()
        if self.sequence is not None:
            self.sequence.set_map([])
        return removed


__all__ = ['Answer', 'LimitError', 'Localizer', 'default_conf']

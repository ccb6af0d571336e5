"""lln-eval --geometry: a TUM RGB-D sequence replayed through the node's code path, and the metric
loop-closure figures of issue 27 in results.json's `geometry` object.

    out = evaluate_geometry(read_tum(root, {'step': 3}), Extractor(), conf)

Per frame, in stamp order, as the matcher in mapping mode does it: the extractor core's landmark set
(core.extractor.Extractor, as the extractor node calls it), ORB keypoints (reloc.Relocalizer.detect,
as the extractor node's publish_keypoints), the Localizer's answer (core.localizer.Localizer on a
real SQLite map in mapping mode: the query is stored as a keyframe after it is answered, keyframes
newer than min_gap_s are excluded), keypoint matches constrained to the best candidate's matched
landmark regions (core.reloc.region_boxes, Relocalizer.match) and core.geometry.estimate_pose twice:
with the keyframe's depth (PnP) and without it (essential matrix). The keyframe's stored pose and
the query's odometry are the ground truth (what an odometry source with no drift would give; the
Agreement check uses them).

Thresholds are chosen (geometry_score.choose) on the queries of one part of the sequence and the
figures reported on the queries of the other: choose = frames before split (default the first
half), report = the rest. Both parts are named in the output.
"""

from __future__ import annotations

import json
import tempfile
import time
from pathlib import Path

import numpy as np

from ..core import geometry
from . import geometry_score as gs

eval_conf = {
    'step': 3,  # every 3rd frame of a 30 Hz sequence: 10 Hz, the rate a matcher would be fed at
    'min_gap_s': 2.0,  # answers must be at least this much older than the query (the poses: reader's default)
    'revisit_deg': 15.0,  # a query is a true revisit when an allowed keyframe is within these
    'revisit_m': 0.3,
    'split': 0.5,  # fraction of the frames whose queries choose the thresholds; the rest report
    'swap': False,  # True: the later part chooses, the first part reports (the same check the other way)
    'k': 5,  # candidates the Localizer answers; the geometry runs on the best
    'max_keypoints': 1000,  # ORB keypoints per image (reloc's default)
    'margin': 1.0,  # region growth in cells (reloc's default)
    # gate: instead of mapping mode (every query stored, the newest N keyframes excluded), queries in
    # localization mode and keyframes chosen by core.gating.KeyframeGate on the odometry, held back
    # until min_gap_s old (core.gating.HeldKeyframes): the matcher's keyframes topic fed by a gate
    'gate': False,
    'gate_m': 0.05,
    'gate_deg': 10.0,
    # novelty > 0 (no odometry, the gate a robot without odometry gets): mapping mode stores a query
    # only when its best S is below this (registration's keyframe_novelty_max_score), and answers
    # must be min_gap_s older in seconds (exclude_recent_s), since frames no longer count keyframes
    'novelty': 0.0,
}


def replay(seq, extractor, conf: dict | None = None, progress: bool = False) -> tuple[list, dict]:
    """(records as geometry_score describes them, timing {stage: median ms}) for an RGBDSequence."""
    from ..core.gating import HeldKeyframes, KeyframeGate
    from ..core.localizer import Localizer
    from ..core.registration import best_raw_score
    from ..core.reloc import Relocalizer, region_boxes
    from ..io.image import load_image
    from ..mapstore import open_for_matcher

    c = {**eval_conf, **(conf or {})}
    reloc = Relocalizer({'detector': 'orb', 'max_keypoints': int(c['max_keypoints']), 'margin': c['margin']})
    stamps = np.array([f.stamp for f in seq.frames])
    poses = [seq.T_world_cam(i) for i in range(len(seq))]
    # mapping mode excludes the newest N keyframes: N frames at this sequence's rate cover min_gap_s
    period = float(np.median(np.diff(stamps))) if len(stamps) > 1 else 1.0
    exclude = int(np.ceil(float(c['min_gap_s']) / period))
    records, ms = [], {'extract': [], 'detect': [], 'query': [], 'match': [], 'pnp': [], 'essential': []}
    keypoints, frame_of = {}, {}  # keyframe id -> reloc.Keypoints, frame index
    with tempfile.TemporaryDirectory(prefix='lln_geometry_') as tmp:
        store, _ = open_for_matcher(str(Path(tmp) / 'map.db'), 'mapping', extractor.descriptor_space)
        with store:
            gated, novelty = bool(c['gate']), float(c['novelty'])
            # the ungated protocol stores every query (novelty gating off), as the figures say
            reg, newest = {'keyframe_novelty_max_score': 0.0}, exclude
            if novelty > 0:
                reg, newest = {'keyframe_novelty_max_score': novelty, 'exclude_recent_s': float(c['min_gap_s'])}, 0
            every = {'mode': 'mapping', 'exclude_recent': newest, 'registration': reg}
            mode = {'mode': 'localization'} if gated else every
            loc = Localizer(store, {**mode, 'k': int(c['k'])})
            gate = KeyframeGate({'min_distance_m': c['gate_m'], 'min_angle_deg': c['gate_deg']})
            held = HeldKeyframes(c['min_gap_s'])
            loc.model_info(json.dumps(extractor.model_info))
            items = range(len(seq))
            if progress:
                from tqdm import tqdm

                items = tqdm(items, desc='geometry replay', leave=False)
            for i in items:
                rgb = load_image(str(seq.frames[i].rgb))
                seq.camera.check_image(rgb.shape[1], rgb.shape[0])
                t0 = time.perf_counter()
                lset = extractor(rgb)
                t1 = time.perf_counter()
                kq = reloc.detect(rgb)
                ms['detect'].append((time.perf_counter() - t1) * 1e3)
                for j_lset, j_kps, j in held.ready(stamps[i]):  # old enough to answer now
                    kid = loc.keyframe(j_lset, int(round(stamps[j] * 1e9)))
                    keypoints[kid], frame_of[kid] = j_kps, j
                t2, stored_before = time.perf_counter(), len(store)
                answer = loc.query(lset, int(round(stamps[i] * 1e9)))
                ms['extract'].append((t1 - t0) * 1e3)
                ms['query'].append((time.perf_counter() - t2) * 1e3)
                if not gated and len(store) > stored_before:
                    kid = store.ids()[-1]  # mapping mode stored this query as the newest keyframe
                    keypoints[kid], frame_of[kid] = kq, i
                elif gate.decide(stamps[i], poses[i])[0]:
                    held.add(stamps[i], (lset, kq, i))
                allowed = stamps[i] - stamps >= float(c['min_gap_s'])
                rec = {
                    'frame': i,
                    'keyframe_frame': None,
                    'score': float('nan'),
                    'revisit': bool(_revisit(poses, i, allowed, c)),
                    'T_odom': poses[i],
                    'T_map_keyframe': None,
                    'T_gt': None,
                    'est_depth': None,
                    'est_mono': None,
                }
                best = answer.best if answer is not None else None
                if best is not None:
                    j = frame_of[best.keyframe_id]
                    p = best.pairs
                    qb = region_boxes(np.stack([p['query_u'], p['query_v']], axis=1), lset.cell_size, c['margin'])
                    mb = region_boxes(
                        np.stack([p['map_u'], p['map_v']], axis=1),
                        np.stack([p['cell_w'], p['cell_h']], axis=1),
                        c['margin'],
                    )
                    matches = reloc.match(kq, keypoints[best.keyframe_id], qb, mb)
                    ms['match'].append(matches.ms)
                    kk, cam = keypoints[best.keyframe_id], seq.camera
                    est_d = geometry.estimate_pose(kq, kk, matches, cam, cam, seq.depth_m(j))
                    est_m = geometry.estimate_pose(kq, kk, matches, cam, cam, None)
                    ms['pnp' if est_d.method == 'pnp' else 'essential'].append(est_d.ms)
                    ms['essential'].append(est_m.ms)
                    rec.update(
                        keyframe_frame=j,
                        score=best_raw_score([best]),  # accept()'s min_score is in raw S
                        T_map_keyframe=poses[j],
                        T_gt=geometry.invert(poses[j]) @ poses[i],
                        est_depth=est_d,
                        est_mono=est_m,
                    )
                records.append(rec)
            n_keyframes = len(store)
    timing = {k: float(np.median(v)) if v else None for k, v in ms.items()}
    return records, {**timing, 'exclude_recent_frames': exclude, 'keyframes': n_keyframes}


def _revisit(poses: list, i: int, allowed: np.ndarray, c: dict) -> bool:
    """Some allowed earlier frame is within revisit_deg and revisit_m of frame i."""
    for j in np.flatnonzero(allowed):
        T = geometry.invert(poses[j]) @ poses[i]
        if np.linalg.norm(T[:3, 3]) <= c['revisit_m'] and geometry.rotation_deg(T[:3, :3]) <= c['revisit_deg']:
            return True
    return False


def evaluate_geometry(seq, extractor, conf: dict | None = None, progress: bool = False) -> dict:
    """The `geometry` object of results.json (module doc)."""
    c = {**eval_conf, **gs.score_conf, **(conf or {})}
    records, timing = replay(seq, extractor, c, progress)
    cut = int(round(float(c['split']) * len(records)))
    first = f'queries of frames 0-{cut - 1} (the first {c["split"]:g} of {seq.name}, step {seq.info.get("step")})'
    rest = f'queries of frames {cut}-{len(records) - 1} (the rest; answers may be any earlier keyframe)'
    parts = {'choose': records[:cut], 'report': records[cut:]}
    if c['swap']:
        parts, first, rest = {'choose': parts['report'], 'report': parts['choose']}, rest, first
    out = {
        'dataset': seq.name,
        'frames': len(seq),
        'step': seq.info.get('step'),
        'choose_part': first,
        'report_part': rest,
        'revisit': {'max_deg': c['revisit_deg'], 'max_m': c['revisit_m'], 'min_gap_s': c['min_gap_s']},
        'false_fix': {'max_m': c['false_m'], 'max_deg': c['false_deg']},
        'odometry': 'ground truth (the keyframe poses and the Agreement check)',
        'keyframes': timing.pop('keyframes'),
        'keyframes_from': (
            f'KeyframeGate on the odometry ({c["gate_m"]:g} m / {c["gate_deg"]:g} deg), held {c["min_gap_s"]:g} s'
            if c['gate']
            else f'mapping mode, no odometry: a query stored when its best S < {c["novelty"]:g} (novelty), '
            f'answers at least {c["min_gap_s"]:g} s older'
            if c['novelty'] > 0
            else f'mapping mode: every query, the newest {timing["exclude_recent_frames"]} excluded'
        ),
        'timing_ms_median': timing,
        'answered': sum(r['est_depth'] is not None for r in records),
    }
    for name, key in (('with_depth', 'est_depth'), ('without_depth', 'est_mono')):
        rule, chosen = gs.choose(parts['choose'], key, c)
        report = gs.figures(parts['report'], key, gs.decide(parts['report'], key, rule), c)
        out[name] = {
            'rule': rule,
            'choose': chosen,
            'report': report,
            'targets': gs.TARGETS[name],
            'met': gs.met(report, gs.TARGETS[name]),
            'methods': _methods(parts['report'], key),
        }
    # the names at the top of the object: the reported (held-out) figures with depth
    for k in ('rot_err_deg_p50', 'rot_err_deg_p95', 'trans_err_m_p50', 'trans_err_m_p95'):
        out[k] = out['with_depth']['report'].get(k)
    out['transform_recall'] = out['with_depth']['report']['transform_recall']
    out['false_fix_rate'] = out['with_depth']['report']['false_fix_rate']
    out['without_depth_rot_err_deg_p50'] = out['without_depth']['report']['rot_err_deg_p50']
    out['without_depth_trans_dir_err_deg_p50'] = out['without_depth']['report']['trans_dir_err_deg_p50']
    return out


def _methods(records: list, key: str) -> dict:
    """How many answered queries were solved by which method (PnP falls back without depth points)."""
    counts: dict = {}
    for r in records:
        est = r[key]
        if est is not None:
            name = est.method or 'none'
            counts[name] = counts.get(name, 0) + 1
    return counts


def write(out_dir, geometry_obj: dict, command: str = '') -> Path:
    """results.json in out_dir with `geometry` set (other keys of an existing file are kept)."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    path = out_dir / 'results.json'
    data = json.loads(path.read_text()) if path.is_file() else {}
    data['geometry'] = {**geometry_obj, **({'command': command} if command else {})}
    path.write_text(json.dumps(data, indent=2, default=_json) + '\n')
    return path


def _json(o):
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(type(o).__name__)

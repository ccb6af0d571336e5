"""What one hostile message costs the matcher's decoding and decisions, next to a good query, and
the worst-case cost of one message of each kind at the limits (docs/interfaces.md).

    python bench/bench_hostile.py [--keyframes 300] [--repeat 5]

A real SQLite map (in a temporary folder) of synthetic keyframes with the default model's shapes
(n=50, D=192, 12x9 grid at 384x288). Each message goes through what the node does with it:
msgs.cloud_to_landmarks with the node's limits, then Localizer.query. Per message: the median
time of --repeat runs, then the peak of traced allocations of one more run (tracemalloc; numpy
reports its arrays to it), printed as a table with the outcome (answered / the counter it was refused under).

The second table, "worst-case cost of one message": each kind of message at the default limits
(lln_ros.core.limits.default_conf), through the same code the node runs for it: a query and a
keyframe of max_landmarks (4,096) landmarks at D=192 into the same map (which then holds one
4,096-landmark keyframe, so the query's candidates include it), a keypoints cloud of max_keypoints
rows (verify: decoded when its landmark set arrives), a model_info at its size and depth bounds,
a cloud of max_point_fields fields and one of 40,000 (refused), a raw image and a JPEG at
max_image_pixels (the codec only; the network's cost at that size: bench/bench_large_images.py).
tracemalloc sees numpy and Python allocations, not FAISS's own (the landmark index search of a
4,096-landmark query is ~4096 x landmark_knn results); the node-level VmHWM of the same messages is
measured over DDS by test/test_hostile_round2.py.
"""

from __future__ import annotations

import argparse
import array
import os
import statistics
import sys
import tempfile
import time
import tracemalloc
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_integrity import SPACE, synthetic  # noqa: E402

from lln_ros.core.localizer import Localizer  # noqa: E402
from lln_ros.errors import MessageError  # noqa: E402
from lln_ros.mapstore import open_for_matcher as open_map  # noqa: E402
from lln_ros.ros import msgs  # noqa: E402


def hostile(good) -> dict:
    base = msgs.cloud_to_array(msgs.landmarks_to_cloud(good))
    col, row = np.floor(base['u'][1:] / base['w'][1:]), np.floor(base['v'][1:] / base['h'][1:])
    tiny = base.copy()
    tiny['w'][1:], tiny['h'][1:] = 1e-3, 1e-3
    tiny['u'][1:], tiny['v'][1:] = (col + 0.5) * 1e-3, (row + 0.5) * 1e-3
    huge = base.copy()
    huge['w'][0], huge['h'][0] = 1e9, 1e9
    wide = base.copy()
    wide['w'][0] = 32768
    many = np.zeros(100_001, base.dtype)
    many[0], many[1:] = base[0], base[1]
    truncated = msgs.array_to_cloud(base)
    truncated.data = array.array('B', bytes(truncated.data)[:-7])
    return {
        'good query': msgs.array_to_cloud(base),
        'cell 1e-3 px': msgs.array_to_cloud(tiny),
        'image 1e9 x 1e9': msgs.array_to_cloud(huge),
        'image 32768 px wide': msgs.array_to_cloud(wide),
        '100k landmark rows': msgs.array_to_cloud(many),
        'truncated data': truncated,
    }


def handle(loc: Localizer, cloud) -> str:
    before = loc.counters.snapshot()
    try:
        lset = msgs.cloud_to_landmarks(cloud, **loc.landmark_decoding('bad_query'))
    except MessageError as e:
        loc.refuse('bad_query', e)
        return 'bad_query'
    answer = loc.query(lset, 1)
    if answer is not None:
        return f'answered ({len(answer.rows)} rows)'
    after = loc.counters.snapshot()
    return next(k for k in after if after[k] != before.get(k, 0))


def measure(fn, repeat: int) -> tuple[float, float, str]:
    """(median ms of repeat runs, traced peak MiB of one more run, outcome) of fn() -> outcome."""
    times, outcome = [], ''
    for _ in range(repeat):
        start = time.perf_counter()
        outcome = fn()
        times.append(time.perf_counter() - start)
    tracemalloc.start()
    fn()
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    return statistics.median(times) * 1e3, peak / 2**20, outcome


def long_set(rng, n: int = 4096, base=None):
    """n landmarks on the widest grid the limits allow at 288 px (9 x max_grid_side 128 cells of 32
    px; landmarks share cells), D=192; base: a noisy view of that set (a query of its place)."""
    from lln_ros.core.landmarks import LandmarkSet

    if base is None:
        desc = rng.standard_normal((n, 192))
        cells = np.stack([rng.integers(0, 128, n), rng.integers(0, 9, n)], axis=1).astype(np.int32)
    else:
        desc, cells = base.descriptors + 0.3 * rng.standard_normal(base.descriptors.shape), base.cells
    desc = (desc / np.linalg.norm(desc, axis=1, keepdims=True)).astype(np.float32)
    glob = desc.mean(0) / np.linalg.norm(desc.mean(0))
    return LandmarkSet(
        global_descriptor=glob.astype(np.float32),
        descriptors=desc,
        cells=cells,
        centers=(cells * 32 + 16).astype(np.float32),
        scores=np.linspace(1, 0, n, dtype=np.float32),
        cell_size=np.array([32, 32], np.float32),
        image_size=np.array([4096, 288], np.float32),
        grid=(9, 128),
        descriptor_space=SPACE,
    )


def worst_case(loc: Localizer, rng, repeat: int) -> list[tuple]:
    """Rows (message, wire MiB, ms, peak MiB, outcome) of one message of each kind at the limits."""
    import json

    import cv2
    from sensor_msgs.msg import CompressedImage, PointField

    from lln_ros.core import limits as lim
    from lln_ros.core.reloc import Keypoints

    rows = []
    kf = long_set(rng)
    kf_cloud = msgs.landmarks_to_cloud(kf)
    stamps = iter(range(10**6, 2 * 10**6))

    def keyframe():
        lset = msgs.cloud_to_landmarks(kf_cloud, **loc.landmark_decoding('bad_keyframe'))
        return 'stored' if loc.keyframe(lset, next(stamps)) is not None else 'refused'

    # the keyframe first, once: every later query's candidates may include it
    rows.append(('keyframe 4096 landmarks', len(kf_cloud.data) / 2**20, *measure(keyframe, 1)))
    query_cloud = msgs.landmarks_to_cloud(long_set(rng, base=kf))
    rows.append(
        ('query 4096 landmarks', len(query_cloud.data) / 2**20, *measure(lambda: handle(loc, query_cloud), repeat))
    )
    ordinary = msgs.landmarks_to_cloud(synthetic(rng, 1)[0])
    rows.append(('query 50 (after both)', len(ordinary.data) / 2**20, *measure(lambda: handle(loc, ordinary), repeat)))
    n = lim.default_conf['max_keypoints']
    kps = Keypoints.empty((4096, 288))
    kps.uv = rng.random((n, 2)).astype(np.float32) * 288
    kps.size, kps.angle = np.full(n, 31, np.float32), np.zeros(n, np.float32)
    kps.response, kps.octave = np.ones(n, np.float32), np.zeros(n, np.int32)
    kps.descriptors = rng.integers(0, 256, (n, 32), dtype=np.uint8)
    kp_cloud = msgs.keypoints_to_cloud(kps)
    rows.append(
        (
            f'keypoints {n} rows',
            len(kp_cloud.data) / 2**20,
            *measure(lambda: f'{len(msgs.cloud_to_keypoints(kp_cloud, (4096, 288), 1.0, n).uv)} decoded', repeat),
        )
    )
    depth = lim.MODEL_JSON_MAX_DEPTH - 1
    model = json.dumps({'descriptor_space': SPACE, 'descriptor_dim': 192})[:-1]
    pad = lim.MODEL_JSON_MAX_BYTES - len(model) - 2 * depth - 40
    for name, text in (
        ('model_info 64 KiB, depth 8', f'{model}, "x": {"[" * depth}"{"y" * pad}"{"]" * depth}}}'),
        ('model_info nested 1000', f'{model}, "x": {"[" * 1000}{"]" * 1000}}}'),
    ):

        def model_info(text=text):
            before = loc.counters.snapshot().get('bad_model_info', 0)
            loc.model_info(text)
            return 'bad_model_info' if loc.counters.snapshot().get('bad_model_info', 0) > before else 'accepted'

        rows.append((name, len(text) / 2**20, *measure(model_info, repeat)))
    for extra in (lim.default_conf['max_point_fields'] - 6, 40_000):
        wide = msgs.landmarks_to_cloud(synthetic(rng, 1)[0])
        wide.fields = list(wide.fields) + [
            PointField(name=f'f{i}', offset=0, datatype=2, count=1) for i in range(extra)
        ]
        rows.append(
            (f'query {6 + extra} PointFields', len(wide.data) / 2**20, *measure(lambda w=wide: handle(loc, w), repeat))
        )
    side_w, side_h = 8192, lim.default_conf['max_image_pixels'] // 8192
    image = np.zeros((side_h, side_w, 3), np.uint8)
    image[::64] = 255
    raw = msgs.array_to_image(image, 'rgb8')
    rows.append(
        (
            f'raw image {side_w}x{side_h} rgb8',
            len(raw.data) / 2**20,
            *measure(lambda: f'decoded {msgs.message_to_array(raw, lim.default_conf["max_image_pixels"])[0].shape}', 1),
        )
    )
    ok, jpg = cv2.imencode('.jpg', image)
    comp = CompressedImage(format='jpeg', data=array.array('B', jpg.tobytes()))
    rows.append(
        (
            f'jpeg {side_w}x{side_h}',
            len(comp.data) / 2**20,
            *measure(
                lambda: f'decoded {msgs.message_to_array(comp, lim.default_conf["max_image_pixels"])[0].shape}', 1
            ),
        )
    )
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--keyframes', type=int, default=300)
    ap.add_argument('--repeat', type=int, default=5)
    args = ap.parse_args(argv)
    rng = np.random.default_rng(0)
    sets = synthetic(rng, args.keyframes)
    with tempfile.TemporaryDirectory() as tmp:
        store, _ = open_map(os.path.join(tmp, 'map.db'), descriptor_space=SPACE)
        with store:
            store.add_many(sets, [(i, 0) for i in range(len(sets))])
            loc = Localizer(store, log=_Quiet())
            rows = []
            for name, cloud in hostile(sets[7]).items():
                times, peaks, outcome = [], [], ''
                for _ in range(args.repeat):  # timed without tracemalloc, which slows allocation
                    start = time.perf_counter()
                    outcome = handle(loc, cloud)
                    times.append(time.perf_counter() - start)
                tracemalloc.start()
                handle(loc, cloud)
                peaks.append(tracemalloc.get_traced_memory()[1])
                tracemalloc.stop()
                wire = len(cloud.data) / 2**20
                rows.append((name, wire, statistics.median(times) * 1e3, max(peaks) / 2**20, outcome))
            worst = worst_case(loc, rng, args.repeat)
    load = ' '.join(f'{x:.1f}' for x in os.getloadavg())
    print(f'map: {args.keyframes} keyframes (n=50, D=192); load average {load} on {os.cpu_count()} cores')
    print(f'{"message":<22}{"on the wire MB":>15}{"ms":>9}{"peak alloc MB":>15}  outcome')
    for name, wire, ms, peak, outcome in rows:
        print(f'{name:<22}{wire:>15.2f}{ms:>9.2f}{peak:>15.2f}  {outcome}')
    print('\nworst-case cost of one message (default limits; D=192; the map above plus the keyframe row)')
    print(f'{"message":<30}{"wire MiB":>10}{"ms":>10}{"peak MiB":>10}  outcome')
    for name, wire, ms, peak, outcome in worst:
        print(f'{name:<30}{wire:>10.2f}{ms:>10.1f}{peak:>10.1f}  {outcome}')
    return 0


class _Quiet:
    def warning(self, text):
        pass

    error = info = warning


if __name__ == '__main__':
    sys.exit(main())

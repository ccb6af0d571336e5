"""Exact vs compressed (IVF-PQ) search of the landmark index on descriptors of real images.

    python bench/bench_landmark_index.py [--keyframes 100000] [--cache out/real_landmarks.npz]
                                         [--augment 1] [--queries 500] [--knn 20] [--nprobe 8,16,32]
                                         [--index-top 0,25] [--query-top N] [--refine SQ8] [--k-factor 4,8]
                                         [--lists 0,4096]
                                         [--hnsw 16:SQ8,32:SQ8 --ef 32,64,128]

The map: the landmark sets (n=50, the default extractor: efficientnet_lite0/stage6, D=192) of every
image of every real dataset in ../shared/data (nordland_trimmed summer + winter, rtabmap_loop,
essex3in1 query + ref, tum_fr1rpy rgb), each also extracted from --augment photometric/geometric
augmentations of the same image (aug 1: mirrored left-right, gamma 0.7; aug k>1: a random crop of
80-95% of each side resized back, brightness x0.6-1.4), so every
descriptor is a real network output on a real (transformed) photo. Until the map reaches
--keyframes x 50 landmarks these real ones are repeated, each repeat with a fresh Gaussian
perturbation of norm 0.1 (then renormalised) -- the repeats are the only synthetic part, and the
table says how many landmarks are real. Queries: landmarks of every 8th real image seen
through one more random crop + brightness augmentation the map does not hold (no query landmark is
in the map verbatim), --queries of them.

recall@k = |compressed top k  &  exact top k| / k per query landmark (exact = brute-force inner
product over the same float32 vectors: the real ones prepared as the shipped index holds them,
LandmarkIndex.prepare -- centred per set (landmark_center), then whitened with the descriptor space's
shipped W (landmark_whitening)), at knn (the first stage's k) and 1, per --kinds x --nprobe, with the
search time per query set (50 landmarks, or its best --query-top; one call per set, as a query searches,
the fastest of three passes, 1 thread; 'of which lists': the part that finds the IVF lists to probe) of each
(ivfpq-fs-refine: with its re-ranking of landmark_k_factor x knn candidates, --k-factor N[,M], on --refine
codes). --index-top N[,M]: the map holds each set's best N landmarks (landmark_index_top, centred on
all 50), --keyframes x N in all (a map per value, the same queries); --query-top N: each query set's
best N search (landmark_query_top). --hnsw M:CODES: FAISS HNSW graphs over the same map at each --ef,
built with OMP_NUM_THREADS threads (1 unless set), searched with one (issue 30's HNSW lever; the map
stores cannot hold one: FAISS's HNSW has no delete).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

for _var in ('OPENBLAS_NUM_THREADS', 'OMP_NUM_THREADS', 'MKL_NUM_THREADS'):
    os.environ.setdefault(_var, '1')

import numpy as np  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
QUERY_EVERY = 8  # a query view of every 8th image (~1k query sets)
DATA = Path(os.environ.get('LLN_DATA') or REPO.parent / 'shared' / 'data')


def real_images() -> list[Path]:
    """Every image of every real dataset (README of ../shared/data), sorted per folder."""
    from lln_ros.io.datasets import list_images

    folders = [
        DATA / 'nordland_trimmed' / 'summer',
        DATA / 'nordland_trimmed' / 'winter',
        DATA / 'rtabmap_loop',
        DATA / 'essex3in1' / 'query',
        DATA / 'essex3in1' / 'ref',
        DATA / 'tum_fr1rpy' / 'rgb',
    ]
    missing = [str(f) for f in folders if not f.is_dir()]
    if missing:
        sys.exit(f'bench_landmark_index: real data not found: {missing} (set LLN_DATA)')
    return [p for f in folders for p in list_images(f)]


def augment(img: np.ndarray, k: int, rng) -> np.ndarray:
    """Augmentation k of an RGB uint8 image (module doc); k = 0 is the image itself."""
    import cv2

    if k == 0:
        return img
    out = img.astype(np.float32)
    if k == 1:
        out = 255.0 * (out[:, ::-1] / 255.0) ** 0.7
    else:
        h, w = img.shape[:2]
        ch, cw = (int(round(s * rng.uniform(0.8, 0.95))) for s in (h, w))
        y, x = rng.integers(0, h - ch + 1), rng.integers(0, w - cw + 1)
        out = cv2.resize(out[y : y + ch, x : x + cw], (w, h), interpolation=cv2.INTER_LINEAR)
        out = out * rng.uniform(0.6, 1.4)
    return np.clip(out, 0, 255).astype(np.uint8)


def interleaved(paths: list[Path]) -> list[Path]:
    """Every image once, the datasets interleaved (each in a fixed random order), so that any
    prefix of the list samples every dataset in proportion: an extraction stopped early still
    covers all of them."""
    rng = np.random.default_rng(0)
    groups: dict[str, list[Path]] = {}
    for p in paths:
        groups.setdefault(str(p.parent), []).append(p)
    keyed = []
    for g in groups.values():
        order = rng.permutation(len(g))
        keyed += [((r + 0.5) / len(g), g[i]) for r, i in enumerate(order)]
    order = [p for _, p in sorted(keyed, key=lambda t: t[0])]
    # the Nordland test split (the last 30% of both seasons) first, whole: its sets are also what
    # the first-stage quality check (--nordland) ranks
    test = nordland_test()
    first = set(test.ref_paths) | set(test.query_paths)
    return list(test.ref_paths) + list(test.query_paths) + [p for p in order if p not in first]


def nordland_test():
    """The Nordland test split as lln-eval reads it (scripts/results.sh: --range 0.7:1)."""
    from lln_ros.io import datasets

    root = DATA / 'nordland_trimmed'
    ds = datasets.parse_spec(f'aligned:{root / "summer"},{root / "winter"},1', (0.7, 1.0))
    ds.ref_paths, ds.query_paths = [Path(p) for p in ds.ref_paths], [Path(p) for p in ds.query_paths]
    return ds


def descriptor_space(data: dict) -> str:
    """The descriptor space of the cache's landmarks (recorded since the index holds whitened
    vectors; a cache without it was made by the default extractor, whose space this is)."""
    if 'space' in data:
        return str(data['space'])
    from lln_ros.core.extractor import Extractor

    return Extractor({'num_threads': 1}).descriptor_space


def extract(cache: Path, augs: int, limit: int = 0) -> dict:
    """Landmarks of the real images (interleaved, the first `limit`; 0 = all) x (1 + augs) views, and
    of a query view of every QUERY_EVERY-th; cached in `cache`, written every 200 images, so a run
    can be stopped and resumed (a later run with the same augs continues where it stopped)."""
    data = dict(np.load(cache)) if cache.exists() else None
    if data is not None and int(data['augs']) != augs:
        data = None
    paths = interleaved(real_images())[: limit or None]
    done = 0 if data is None else len(data['source'])
    if done >= len(paths):
        return data
    from lln_ros.core.extractor import Extractor
    from lln_ros.io.image import load_image

    ex = Extractor({'num_threads': 1})
    desc = [] if data is None else list(data['descriptors'])
    qdesc = [] if data is None else list(data['query_descriptors'])
    cells = [] if data is None else list(data['cells'])
    qcells = [] if data is None else list(data['query_cells'])
    source = [] if data is None else list(data['source'])
    t = time.perf_counter()
    for n in range(done, len(paths)):
        p = paths[n]
        rng = np.random.default_rng(n)  # per image: a resumed run makes the same views
        img = load_image(str(p))
        query = n % QUERY_EVERY == 0
        views = [augment(img, k, rng) for k in range(1 + augs)]
        if query:  # the query view: an augmentation the map does not hold
            views.append(augment(img, 2 + augs, rng))
        sets = ex.extract_batch(views)
        desc.extend(s.descriptors.astype(np.float16) for s in sets[: 1 + augs])
        cells.extend(s.cells.astype(np.int16) for s in sets[: 1 + augs])
        if query:
            qdesc.append(sets[-1].descriptors.astype(np.float16))
            qcells.append(sets[-1].cells.astype(np.int16))
        source.append(str(p.relative_to(DATA)))
        if (n + 1) % 200 == 0 or n + 1 == len(paths):
            data = {
                'descriptors': np.stack(desc),  # (images x (1 + augs), 50, D) float16
                'cells': np.stack(cells),  # (images x (1 + augs), 50, 2) int16 (col, row)
                'query_descriptors': np.stack(qdesc),  # (images / QUERY_EVERY, 50, D)
                'query_cells': np.stack(qcells),
                'source': np.array(source),  # path under ../shared/data of each image
                'augs': np.array(augs),
                'space': np.array(ex.descriptor_space),
            }
            cache.parent.mkdir(parents=True, exist_ok=True)
            np.savez(str(cache) + '.tmp.npz', **data)
            os.replace(str(cache) + '.tmp.npz', cache)
            print(f'{n + 1}/{len(paths)} images, {time.perf_counter() - t:.0f} s', file=sys.stderr)
    return data


def unit(x: np.ndarray) -> np.ndarray:
    return (x / np.linalg.norm(x, axis=-1, keepdims=True)).astype(np.float32)


def grow(real: np.ndarray, total: int, noise: float, rng) -> np.ndarray:
    """real (R, D) repeated up to `total` rows, every repeat after the first perturbed by a random
    direction of norm `noise` and renormalised (module doc)."""
    out = [real]
    have = len(real)
    while have < total:
        part = real[: min(len(real), total - have)]
        out.append(unit(part + noise * unit(rng.standard_normal(part.shape).astype(np.float32))))
        have += len(part)
    return np.concatenate(out)


def per_set_search(search, q: np.ndarray, sets: int, passes: int = 3) -> tuple[np.ndarray, float]:
    """search(part) -> ids (n, k) called once per query set of q (sets parts), as a query searches (one
    batch of them all costs less per set): (the ids of every part stacked, ms per set of the fastest
    of `passes` passes: this host's neighbours come and go)."""
    parts, ms = np.array_split(q, sets), float('inf')
    for _ in range(passes):
        t = time.perf_counter()
        got = np.concatenate([search(part) for part in parts])
        ms = min(ms, (time.perf_counter() - t) / sets * 1000)
    return got, ms


def exact_knn(x: np.ndarray, q: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Brute-force top k by inner product: sims (Q, k), rows of x (Q, k); x is not copied."""
    import faiss

    return faiss.knn(q, x, k, metric=faiss.METRIC_INNER_PRODUCT)


def index_recall(args, data: dict) -> list[dict]:
    """recall@1 / @knn of every --kinds x --nprobe against exact search (module doc), and the time
    of one query set's search."""
    import faiss

    from lln_ros.core.landmark_index import LandmarkIndex
    from lln_ros.core.threads import one_faiss_thread

    space = descriptor_space(data)
    shipped = LandmarkIndex(data['descriptors'].shape[-1], {}, space)

    def held(sets: np.ndarray, top: int) -> np.ndarray:
        """sets (S, n, D) as an index of landmark_index_top `top` holds them (LandmarkIndex.prepare with
        held=True: one keyframe per set, centred on all n, its first `top`; 0 = all): (S*min(n, top), D)."""
        x = unit(sets.reshape(-1, sets.shape[-1]).astype(np.float32))
        index = LandmarkIndex(sets.shape[-1], {'landmark_index_top': top}, space)
        return index.prepare(x, np.repeat(np.arange(len(sets)), sets.shape[1]), held=True)

    rows = []
    pick = np.random.default_rng(2).permutation(len(data['query_descriptors']))[: args.queries]
    qsets = data['query_descriptors'][pick]  # the same queries for every index top
    q = held(qsets, args.query_top)
    for index_top in (int(t) for t in str(args.index_top).split(',')):
        rng = np.random.default_rng(1)
        real = held(data['descriptors'], index_top)
        total = max(len(real), args.keyframes * min(50, index_top or 50))
        x = grow(real, total, args.noise, rng)
        ids = np.arange(len(x), dtype=np.int64)
        t = time.perf_counter()
        ex_s, ex_i = exact_knn(x, q, args.knn)
        exact_s = time.perf_counter() - t
        print(
            f'map (index top {index_top or "all"}): {len(x):,} landmarks ({len(real):,} real, of '
            f'{len(data["source"]):,} images x '
            f'{1 + int(data["augs"])} views); {len(q):,} query landmarks ({len(qsets)} sets); exact search '
            f'{exact_s / len(qsets) * 1000:.0f} ms per set; median cosine of the exact 1st / {args.knn}th '
            f'neighbour {np.median(ex_s[:, 0]):.3f} / {np.median(ex_s[:, -1]):.3f}; whitening '
            f'{"on" if shipped.whitening is not None else "off"}, centring {shipped.conf["landmark_center"]}',
            flush=True,
        )
        for kind, lists in ((k, int(n)) for k in args.kinds.split(',') for n in str(args.lists).split(',')):
            conf = {
                'landmark_compressed': kind,
                'landmark_index_threshold': 0,
                'landmark_pq_m': args.pq_m,
                'landmark_ivf_lists': lists,
            }
            if args.refine:
                conf['landmark_refine'] = args.refine
            # x is already what the index holds (held()): no centring, no whitening (no descriptor space),
            # no further selection (ids are not keyframe ids here)
            index = LandmarkIndex(x.shape[1], {**conf, 'landmark_center': False, 'landmark_index_top': 0})
            t = time.perf_counter()
            index.build(x, ids)
            build_s = time.perf_counter() - t
            nbytes = len(faiss.serialize_index(index.index)) + (len(index.refine.to_bytes()) if index.refine else 0)
            factors = [int(v) for v in str(args.k_factor).split(',') if int(v)] if index.refine else []
            for nprobe, k_factor in ((int(n), f) for n in args.nprobe.split(',') for f in factors or [0]):
                index.index.nprobe = nprobe or index.nprobe()  # 0: the kind's default
                if k_factor:  # read at search time: the same index re-ranks a shortlist of k_factor x knn
                    index.conf['landmark_k_factor'] = k_factor
                index.search_prepared(q[:50], args.knn)  # warm
                got, ms = per_set_search(lambda part: index.search_prepared(part, args.knn)[1], q, len(qsets))
                # the part of it that picks the lists: the query against every list's centroid
                with one_faiss_thread():
                    _, coarse_ms = per_set_search(
                        lambda part: index.index.quantizer.search(part, index.index.nprobe)[1], q, len(qsets)
                    )
                hit_k = np.mean([len(set(a) & set(b)) / args.knn for a, b in zip(got, ex_i)])
                hit_1 = float(np.mean(got[:, 0] == ex_i[:, 0]))
                rows.append(
                    {
                        'kind': kind
                        + (f' {index.refine.qtype} k{index.conf["landmark_k_factor"]}' if index.refine else ''),
                        'index_top': index_top,
                        'nprobe': int(index.index.nprobe),
                        'lists': int(index.index.nlist),
                        'recall@1': hit_1,
                        f'recall@{args.knn}': float(hit_k),
                        'ms_per_set': ms,
                        'coarse_ms_per_set': coarse_ms,
                        'build_s': build_s,
                        'bytes_per_landmark': nbytes / len(x),
                    }
                )
                print(rows[-1], flush=True)
        rows += hnsw_recall(args, x, q, ex_i, index_top, len(qsets))
    return rows


def hnsw_recall(args, x: np.ndarray, q: np.ndarray, exact_ids: np.ndarray, index_top: int, sets: int) -> list[dict]:
    """--hnsw M:CODES,...: FAISS HNSW graphs (M links per node, vectors stored as CODES: SQ8, SQ4 or
    Flat) over the same prepared map x (N, D), searched by q (n, D) at each --ef (efSearch), against
    the exact ids (n, knn). Not a kind the map stores can hold: FAISS's HNSW cannot delete."""
    import faiss

    from lln_ros.core.threads import one_faiss_thread

    rows = []
    for spec in filter(None, args.hnsw.split(',')):
        m, codes = spec.split(':')
        t = time.perf_counter()
        index = faiss.index_factory(x.shape[1], f'HNSW{int(m)},{codes}', faiss.METRIC_INNER_PRODUCT)
        index.hnsw.efConstruction = 40
        index.train(x[:: max(1, len(x) // 200_000)])
        index.add(x)
        build_s = time.perf_counter() - t
        nbytes = len(faiss.serialize_index(index))
        for ef in (int(v) for v in args.ef.split(',')):
            params = faiss.SearchParametersHNSW(efSearch=ef)
            index.search(q[:50], args.knn, params=params)  # warm
            with one_faiss_thread():
                got, ms = per_set_search(lambda part, g=index, p=params: g.search(part, args.knn, params=p)[1], q, sets)
            rows.append(
                {
                    'kind': f'hnsw M{m} {codes}',
                    'index_top': index_top,
                    'nprobe': f'ef {ef}',
                    'lists': '-',
                    'recall@1': float(np.mean(got[:, 0] == exact_ids[:, 0])),
                    f'recall@{args.knn}': float(
                        np.mean([len(set(a) & set(b)) / args.knn for a, b in zip(got, exact_ids)])
                    ),
                    'ms_per_set': ms,
                    'coarse_ms_per_set': float('nan'),  # a graph has no lists
                    'build_s': build_s,
                    'bytes_per_landmark': nbytes / len(x),
                }
            )
            print(rows[-1], flush=True)
        del index
    return rows


def nordland_first_stage(args, data: dict) -> list[dict]:
    """The landmark first stage on the Nordland test split (winter queries, summer map, +-1 frame, as
    lln-eval) with each index type: recall@K of its top 100 (no holistic top-up: the index alone)
    and the search + scoring time per query. The sets are the cache's first 2 x 1073 (interleaved()
    puts the test split first)."""
    from lln_ros.core.landmark_index import LandmarkIndex, encode_ids
    from lln_ros.core.landmarks import LandmarkSet
    from lln_ros.core.metrics import recall_at_k

    ds = nordland_test()
    space = descriptor_space(data)
    n_ref, n_q = len(ds.ref_paths), len(ds.query_paths)
    expect = [str(p.relative_to(DATA)) for p in ds.ref_paths + ds.query_paths]
    if len(data['source']) < n_ref + n_q or list(data['source'][: n_ref + n_q]) != expect:
        sys.exit('bench_landmark_index: the cache does not start with the Nordland test split (extract more)')
    desc = unit(data['descriptors'][: n_ref + n_q].astype(np.float32))
    cells = data['cells'][: n_ref + n_q].astype(np.int64)
    d = desc.shape[-1]
    x = desc[:n_ref].reshape(-1, d)
    ids = encode_ids(np.repeat(np.arange(n_ref), desc.shape[1]), cells[:n_ref].reshape(-1, 2))
    queries = [
        LandmarkSet(
            global_descriptor=np.zeros(d, np.float32),
            descriptors=desc[n_ref + i],
            cells=cells[n_ref + i].astype(np.int32),
            centers=np.zeros((desc.shape[1], 2), np.float32),
            scores=np.zeros(desc.shape[1], np.float32),
            cell_size=np.ones(2, np.float32),
            image_size=np.ones(2, np.float32),
            grid=(int(cells[:, :, 1].max()) + 1, int(cells[:, :, 0].max()) + 1),
        )
        for i in range(n_q)
    ]
    configs = ([('exact', 0)] if args.exact else []) + [
        (kind, npb) for kind in args.kinds.split(',') for npb in map(int, args.nprobe.split(','))
    ]
    rows = []
    for kind, nprobe in configs:
        # nprobe 0: the kind's default (landmark_index.NPROBE)
        conf = {'landmark_index_threshold': len(x) if kind == 'exact' else 0, 'landmark_nprobe': nprobe}
        if kind != 'exact':
            conf.update({'landmark_compressed': kind, 'landmark_pq_m': args.pq_m})
            if int(str(args.k_factor).split(',')[0]):  # --nordland: the first factor given
                conf['landmark_k_factor'] = int(str(args.k_factor).split(',')[0])
        index = LandmarkIndex(d, conf, space)  # centred and whitened as the shipped index
        index.build(x, ids)
        ranked = np.full((n_q, 100), -1, np.int64)
        t = time.perf_counter()
        for i, q in enumerate(queries):
            top, _ = index.shortlist(q, 100)
            ranked[i, : len(top)] = top
        ms = (time.perf_counter() - t) / n_q * 1000
        row = {'kind': kind, 'nprobe': index.index.nprobe if kind != 'exact' else 0, 'ms_per_query': ms}
        row.update({f'R@{k}': recall_at_k(ranked, ds.gt, k) for k in (1, 5, 10, 30, 100)})
        rows.append(row)
        print(row, flush=True)
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    ap.add_argument('--cache', default='out/real_landmarks.npz', help='landmarks of the real images (made if absent)')
    ap.add_argument('--augment', type=int, default=0, help='augmented views per image in the map (module doc)')
    ap.add_argument('--limit', type=int, default=0, help='images to extract (interleaved; 0 = all 8,380)')
    ap.add_argument('--keyframes', type=int, default=100_000, help='map size in keyframes of 50 landmarks')
    ap.add_argument('--noise', type=float, default=0.5, help='norm of the perturbation of each repeat')
    ap.add_argument('--queries', type=int, default=20, help='query sets (of 50 landmarks) searched')
    ap.add_argument('--knn', type=int, default=20)
    ap.add_argument('--kinds', default='ivfpq-fs,ivfpq')
    ap.add_argument('--nprobe', default='8,16,32', help='IVF cells probed, each tried (0 = the default of the kind)')
    ap.add_argument('--lists', default='0', help='IVF lists, each tried (0 = sized by the map, the default)')
    ap.add_argument('--pq-m', type=int, default=0, help='PQ sub-quantisers (0 = the default of the kind)')
    ap.add_argument('--k-factor', default='0', help='ivfpq-fs-refine shortlist factor(s), each tried (0 = the default)')
    ap.add_argument('--refine', default='', help="ivfpq-fs-refine re-ranking codes (SQ6|SQ8|...; '' = the default)")
    ap.add_argument(
        '--index-top', default='0', help="each map set's best N landmarks held (landmark_index_top; N,M: a map each)"
    )
    ap.add_argument(
        '--query-top', type=int, default=0, help="each query set's best N landmarks search (landmark_query_top)"
    )
    ap.add_argument(
        '--hnsw', default='', help="FAISS HNSW graphs over the same map, M:CODES,... (e.g. 32:SQ8; '' = none)"
    )
    ap.add_argument('--ef', default='32,64,128', help='--hnsw: efSearch values, each tried')
    ap.add_argument('--no-exact', dest='exact', action='store_false', help='--nordland: skip the exact row')
    ap.add_argument('--nordland', action='store_true', help='the first stage on the Nordland test split instead')
    args = ap.parse_args(argv)
    data = extract(Path(args.cache), args.augment, args.limit)
    if args.nordland:
        rows = nordland_first_stage(args, data)
        print(f'load average {", ".join(f"{v:.2f}" for v in os.getloadavg())}, 1 thread')
        print('| index | nprobe | R@1 | R@5 | R@10 | R@30 | R@100 | ms / query (search + scoring) |')
        print('|---|---|---|---|---|---|---|---|')
        for r in rows:
            print(
                f'| {r["kind"]} | {r["nprobe"] or "-"} | '
                + ' | '.join(f'{r[f"R@{k}"]:.3f}' for k in (1, 5, 10, 30, 100))
                + f' | {r["ms_per_query"]:.1f} |'
            )
        return 0
    rows = index_recall(args, data)
    print(f'load average {", ".join(f"{v:.2f}" for v in os.getloadavg())}, 1 thread')
    per = min(50, args.query_top or 50)
    print(
        f'| index top | index | lists | nprobe | recall@1 | recall@{args.knn} | search ms / {per} landmarks '
        '| of which lists ms | bytes / landmark |'
    )
    print('|---|---|---|---|---|---|---|---|---|')
    for r in rows:
        print(
            f'| {r["index_top"] or "all"} | {r["kind"]} | {r["lists"]} | {r["nprobe"]} | {r["recall@1"]:.3f} '
            f'| {r[f"recall@{args.knn}"]:.3f} '
            f'| {r["ms_per_set"]:.1f} | {r["coarse_ms_per_set"]:.1f} | {r["bytes_per_landmark"]:.0f} |'
        )
    return 0


if __name__ == '__main__':
    if sys.argv[1:2] == ['--extract-only']:  # used to fill the cache in the background
        extract(Path(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4]) if len(sys.argv) > 4 else 0)
        sys.exit(0)
    sys.exit(main())

"""lln-demo's offline side: the same dataset through lln-eval's code (runner.evaluate), run beside
the online one.

The evaluator needs every image's backbone feature map (the nodes publish only the selected
landmarks, not the dense maps its heatmaps and other selections use), so a worker process
(OfflineRun) starts with the nodes: it takes chunks of images from the front of the list into the
feature cache, and when it has them all it runs the evaluation itself, while the query traverse may
still be playing. Once the nodes are done, this process takes chunks from the back until the two
ends meet, then waits for the worker's result. On two cores the comparison then costs little more
wall time than the online run itself. Without a worker (--fps runs, which leave the CPU to the
nodes) run_offline does everything here.

    job = OfflineRun(ds, spec, args, out, log)      # with the nodes
    ...online run...
    offline = run_offline(ds, spec, args, out, log, job)   # the rest; job.stop() on errors
"""

from __future__ import annotations

import multiprocessing
import shlex
import signal
import sys
import time
from pathlib import Path

from .report import METRICS

CHUNK = 8  # images per claim (a claim is one lock round trip)
# images per backbone call while filling: one, as the extractor nodes run it. With one thread, a
# batch is no faster per image on a 2-core machine (slower: the activations of 8 frames leave the
# caches), and the offline features then come from the same batch size as the online ones
BATCH = 1


def extractor_conf(args) -> dict:
    """The Extractor conf of the offline side: the nodes' method, top-n, runtime, weights, threads."""
    from ..cli.common import runtime_conf

    return {
        'top_n': args.top_n,
        'method': 'lln' if args.method == 'holistic' else args.method,
        'num_threads': args.threads,
        **runtime_conf(args),
        'weights': str(Path(args.weights).expanduser().resolve()) if args.weights else '',
    }


def cache_dir(args, out: Path) -> str:
    return args.cache or str(out / 'cache' / 'features')


def eval_conf(args, out: Path) -> dict:
    """runner.evaluate's conf: the nodes' method, top-n and first stage, short timing, the pictures."""
    return {
        'methods': [args.method],
        'top_n': args.top_n,
        'prefilter': args.prefilter,
        'prefilter_k': args.prefilter_k,
        'timing_images': 3,
        'timing_queries': 5,
        'timing_repeats': 1,
        'examples': args.examples,
        'heatmap_images': 4,
        'cache_dir': cache_dir(args, out),
        'plots': True,
        'progress': False,  # the features are in the cache by then; a bar would only flash
    }


def eval_command(spec: str, args, out: Path) -> str:
    return (
        f'lln-eval --dataset {shlex.quote(spec)} --methods {args.method} --top-n {args.top_n} '
        f'--prefilter {args.prefilter} --prefilter-k {args.prefilter_k} --out {shlex.quote(str(out / "offline"))}'
    )


def dataset_paths(ds) -> list[str]:
    """Every distinct image of the dataset, as the evaluator lists them (refs, then queries)."""
    return list(dict.fromkeys([str(p) for p in ds.ref_paths] + [str(p) for p in ds.query_paths]))


def evaluate_one(ds, spec: str, extractor, conf: dict, out: Path, command: str, log) -> dict:
    """runner.evaluate on ds into out/offline; the ranking, summary and entry of its one row."""
    from .runner import evaluate

    t = time.monotonic()
    run = evaluate([ds], extractor, conf, None, out / 'offline', specs=[spec], command=command, log=log)
    name = next(iter(run.datasets))
    row = next(iter(run.datasets[name].rankings))
    ranked, scores = run.datasets[name].rankings[row]
    entry = run.results['datasets'][name]['methods'][row]
    return {
        'ranked': ranked,
        'scores': scores,
        'row': row,
        'summary': {key: entry[key] for key, _ in METRICS},
        'entry': entry,
        'evaluate_seconds': time.monotonic() - t,
        'model': extractor.model_info,
        'results': str(out / 'offline' / 'results.json'),
    }


def _claim(shared, from_back: bool) -> int | None:
    """The next unclaimed chunk from one end (None once the ends have met); a claim from the back
    counts as busy until _release."""
    lock, front, back, busy = shared
    with lock:
        if front.value >= back.value:
            return None
        if from_back:
            back.value -= 1
            busy.value += 1
            return back.value
        front.value += 1
        return front.value - 1


def _release(shared) -> None:
    lock, _, _, busy = shared
    with lock:
        busy.value -= 1


def _worker(paths, ext_conf, cache, height, shared, job, conn) -> None:
    """Worker process: chunks from the front into the cache; then, once the other end's chunks are
    written too, the evaluation (job), its result sent on conn (or {'error': one line})."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's to handle; it terminates us
    try:
        from ..core.extractor import Extractor
        from ..io.features import FeatureCache

        extractor = Extractor(ext_conf)
        store = FeatureCache(cache, extractor, batch_size=BATCH)
        t = time.monotonic()
        while (c := _claim(shared, False)) is not None:
            store.load(paths[c * CHUNK : (c + 1) * CHUNK], size=height)
        while shared[3].value:  # the main process is still writing its last chunks
            time.sleep(0.1)
        features_s = time.monotonic() - t
        if job is None:
            conn.send({'features_seconds': features_s})
            return
        ds, spec, conf, out, command, quiet = job

        def log(msg: str) -> None:
            if not quiet:
                print(f'lln-demo: offline: {msg}', file=sys.stderr, flush=True)

        result = evaluate_one(ds, spec, extractor, conf, out, command, log)
        conn.send({**result, 'features_seconds': features_s, 'evaluated_at': time.monotonic()})
    except Exception as e:  # noqa: BLE001  reported by the parent as the offline side's failure
        conn.send({'error': f'{type(e).__name__}: {e}'})


class OfflineRun:
    """The offline side in a worker process, started with the nodes (see the module doc).

    finish(extractor) fills what is left from the back here and returns the worker's result: the
    evaluate_one dict plus timing and who filled what, or raises RuntimeError with the worker's
    error. stop() ends the worker early (errors, Ctrl-C). Cached entries are only read, so a warm
    cache costs a pass over the file digests. job=False: fill the cache only (tests)."""

    def __init__(self, ds, spec: str, args, out: Path, job: bool = True):
        from ..core.extractor import default_conf

        ctx = multiprocessing.get_context('spawn')  # no fork of a process that runs DDS threads
        ext_conf = extractor_conf(args)
        self.paths, self.cache = dataset_paths(ds), cache_dir(args, out)
        self.height = int(ext_conf.get('input_height', default_conf['input_height']))
        self.chunks = -(-len(self.paths) // CHUNK)
        lock = ctx.Lock()
        # front / back: the next chunk of each end; busy: chunks the main process is writing
        self._shared = (
            lock,
            ctx.Value('i', 0, lock=False),
            ctx.Value('i', self.chunks, lock=False),
            ctx.Value('i', 0, lock=False),
        )
        work = (ds, spec, eval_conf(args, out), out, eval_command(spec, args, out), args.quiet) if job else None
        self._conn, child = ctx.Pipe(duplex=False)
        self.started = time.monotonic()
        self.proc = ctx.Process(
            target=_worker,
            args=(self.paths, ext_conf, self.cache, self.height, self._shared, work, child),
            name='lln-demo-offline',
            daemon=True,
        )
        self.proc.start()
        child.close()

    def progress(self) -> int:
        """Chunks claimed so far (both ends)."""
        lock, front, back, _ = self._shared
        with lock:
            return front.value + self.chunks - back.value

    def finish(self, extractor) -> dict:
        """Fill the rest from the back (here), then wait for the worker's result."""
        from ..io.features import FeatureCache

        lock, front, _, _ = self._shared
        with lock:
            during = front.value
        t = time.monotonic()
        store = FeatureCache(self.cache, extractor, batch_size=BATCH)
        mine = 0
        while (c := _claim(self._shared, True)) is not None:
            try:
                store.load(self.paths[c * CHUNK : (c + 1) * CHUNK], size=self.height)
            finally:
                _release(self._shared)
            mine += 1
        tail = time.monotonic() - t
        while not self._conn.poll(0.5):
            if not self.proc.is_alive():
                break
        try:
            result = self._conn.recv()
        except EOFError:  # it died without a word (killed, out of memory)
            self.proc.join(10)
            raise RuntimeError(f'the offline worker died (exit status {self.proc.exitcode})') from None
        self.proc.join(10)
        if 'error' in result:
            raise RuntimeError(result['error'])
        with lock:
            worker = front.value
        result['cache_fill'] = {
            'images': len(self.paths),
            'chunk': CHUNK,
            'batch': BATCH,
            'chunks_by_worker_during_online': during,
            'chunks_by_worker_after': worker - during,
            'chunks_by_main_after': mine,
            'tail_seconds': tail,
        }
        if 'evaluated_at' in result:  # time.monotonic is system-wide on Linux: one clock for both
            result['evaluation_done_before_online_end_s'] = max(0.0, t - result['evaluated_at'])
        return result

    def stop(self) -> None:
        if self.proc.is_alive():
            self.proc.terminate()
            self.proc.join(5)


def run_offline(ds, spec: str, args, out: Path, log, job: OfflineRun | None = None) -> dict:
    """The offline side's result (evaluate_one's dict, 'seconds' after the online run, and with a
    job its 'cache_fill'): the worker's, after helping it, or computed here without one."""
    from ..core.extractor import Extractor

    t = time.monotonic()
    extractor = Extractor(extractor_conf(args))
    if job is None:
        result = evaluate_one(ds, spec, extractor, eval_conf(args, out), out, eval_command(spec, args, out), log)
        result['cache_fill'] = None
    else:
        log(
            f'lln-demo: offline: {job.progress()} of {job.chunks} feature chunks ({CHUNK} images each) were '
            'computed beside the online run; the rest now from both ends, then the evaluation'
        )
        result = job.finish(extractor)
    result['seconds'] = time.monotonic() - t
    return result

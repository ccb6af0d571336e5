"""One thread for one query's arithmetic: FAISS's OpenMP pool and every BLAS (numpy's OpenBLAS,
FAISS's own) at one thread inside, restored after.

    with one_thread():          # Localizer.query: the matcher's whole answer to one query
        ...
    with one_faiss_thread():    # a FAISS search or k-means alone
        ...

Why: one query's work is small matrices (50 x 192 against a few thousand landmarks) and one kNN, far
too little to split. A second thread only waits at every barrier, and OpenBLAS's idle workers spin
for a while after each call, holding the core the extractor's runtime wants for the next frame.
Frame to answer, int8 runtime, 10k keyframes (bench_frame_to_answer, 2026-12-05, one run each):
p50 24.6 ms and 48.7 CPU ms per frame with two BLAS threads, 21.2 ms and 26.0 CPU ms with one.
"""

from __future__ import annotations

import contextlib
import functools

import faiss
from threadpoolctl import ThreadpoolController


@functools.cache
def _controller() -> ThreadpoolController:
    """The thread pools loaded in this process (found once: finding them takes 0.4-2 ms)."""
    return ThreadpoolController()


@contextlib.contextmanager
def one_faiss_thread():
    """FAISS's OpenMP threads at one inside, restored after: every single-query search and the
    k-means (its threads wait for each other at every barrier, and on a shared 2-core machine for the
    extractor's too; query p50 beside one busy process fell 26.7 -> 13.0 ms at 1k keyframes and 45.2
    -> 17.5 at 10k, bench_frame_to_answer 2026-12-05)."""
    threads = faiss.omp_get_max_threads()
    faiss.omp_set_num_threads(1)
    try:
        yield
    finally:
        faiss.omp_set_num_threads(threads)


@contextlib.contextmanager
def one_thread():
    """one_faiss_thread and every BLAS library of the process at one thread, restored after (~15 us)."""
    with one_faiss_thread(), _controller().limit(limits=1, user_api='blas'):
        yield

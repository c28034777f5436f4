"""Batches of independent poses cut into runs for the machine's cores.

The compiled descent (``descent``) and the exact bead test (``exact_beads``) treat every pose of
a batch alone and release the GIL, so a batch can be cut into contiguous runs of poses, the runs
handed to a few threads and their results joined in pose order. Nothing a pose gets depends on
the cut: the output is the same for any number of threads (``tests/test_split.py``).

Runs are smaller than a thread's share (``RUNS_PER_THREAD`` a thread) so that the few costly poses
of a batch (those in contact, which reach the exact tests) do not hold one thread while the others
wait. Work cut some other way (the bead field's stamp, cut into slabs of its grid where its
chords lie) goes through ``map_parts``. ``$NCFIX_THREADS`` sets the number of threads (1:
everything in the calling thread); the default is the number of cores this process may run on.
"""

from __future__ import annotations

import os
import threading
from concurrent.futures import ThreadPoolExecutor

from ncfix.errors import ConfigError

MIN_RUN = 16  # poses: a smaller batch runs in the calling thread
RUNS_PER_THREAD = 4

_lock = threading.Lock()
_pool: ThreadPoolExecutor | None = None
_threads: int | None = None


def thread_count() -> int:
    """Threads for a batch: ``$NCFIX_THREADS``, else the cores this process may use."""
    text = os.environ.get("NCFIX_THREADS", "").strip()
    if not text:
        try:
            return max(1, len(os.sched_getaffinity(0)))
        except AttributeError:  # pragma: no cover - not Linux
            return max(1, os.cpu_count() or 1)
    try:
        count = int(text)
    except ValueError:
        count = 0
    if count < 1:
        raise ConfigError(f"NCFIX_THREADS is {text!r}", where="environment",
                          fix="set it to a whole number of threads, 1 or more, or unset it")
    return count


def _executor(threads: int) -> ThreadPoolExecutor:
    global _pool, _threads
    with _lock:
        if _pool is None or _threads != threads:
            if _pool is not None:
                _pool.shutdown(wait=True)
            _pool = ThreadPoolExecutor(max_workers=threads, thread_name_prefix="ncfix")
            _threads = threads
        return _pool


def runs(n: int, threads: int) -> list[tuple[int, int]]:
    """Contiguous [lo, hi) runs covering range(n): one when the batch is small or threads is 1."""
    if threads <= 1 or n < 2 * MIN_RUN:
        return [(0, n)]
    count = min(threads * RUNS_PER_THREAD, n // MIN_RUN)
    edges = [n * i // count for i in range(count + 1)]
    return [(edges[i], edges[i + 1]) for i in range(count)]


def map_parts(call, parts: list, threads: int) -> list:
    """[call(*part) for part in parts], in order, for work the caller cuts itself (``runs`` cuts a
    batch into equal runs of poses). The calling thread and up to ``threads`` - 1 of the pool's
    take the parts in turn, each the next one not taken yet when it is free, and the call returns
    once every part is done: a pool thread that does not get a core soon (a shared machine) holds
    up only a part it took, not the others, and with no core free the calling thread does them
    all. The first error a part raised is raised once every part is done."""
    if len(parts) <= 1 or threads <= 1:
        return [call(*part) for part in parts]
    n = len(parts)
    out: list = [None] * n
    errors: list[BaseException] = []
    order = iter(range(n))
    lock = threading.Lock()
    done = [0]
    finished = threading.Event()

    def work():
        while True:
            with lock:
                i = next(order, None)
            if i is None:
                return
            try:
                out[i] = call(*parts[i])
            except BaseException as exc:  # noqa: BLE001 - raised in the calling thread below
                errors.append(exc)
            with lock:
                done[0] += 1
                if done[0] == n:
                    finished.set()

    pool = _executor(threads)
    for _ in range(min(threads, n) - 1):
        pool.submit(work)  # one that starts after the parts are all taken returns at once
    work()
    finished.wait()
    if errors:
        raise errors[0]
    return out


def map_runs(call, n: int) -> list:
    """[call(lo, hi) for each run of range(n)], in run order; the runs on several threads."""
    threads = thread_count()
    parts = runs(n, threads)
    if len(parts) == 1:
        return [call(0, n)]
    return list(_executor(threads).map(lambda run: call(*run), parts))

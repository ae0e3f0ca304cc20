"""Running frames and pairs on worker threads, in a bounded window, with results in frame order.

OpenCV image decoding, SciPy KD-trees, NumPy and Open3D ICP release the GIL, so threads overlap the
work of several frames and pairs. Every job is the same deterministic function whatever thread runs
it, and results are collected in frame order, so the outcome is identical for any number of workers.
Open3D itself is kept to one thread (:func:`single_threaded_open3d`) for the same reason.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

from .errors import ParamError

Progress = Callable[[str, int, int], None]


def single_threaded_open3d() -> None:
    """Keep Open3D to one thread of its own (the pipeline calls this before it runs anything).

    Open3D's threads add up point-to-plane ICP's normal equations in a varying order: the same
    registration then differs in the 14th digit from run to run, enough to flip a decision threshold
    now and then. artclass runs frames and pairs in parallel itself (``workers``), so with Open3D on
    one thread every result is reproducible. It is a process-wide Open3D setting; set here, in one
    place, rather than when a plugin is imported.
    """
    import open3d as o3d

    o3d.utility.set_max_threads(1)


@dataclass
class Job:
    """A frame or pair computed (possibly in a worker thread), with its own stage timings (s)."""

    value: Any
    timing: dict[str, float]


def executor(workers: int):
    """Runs jobs on ``workers`` threads, or at once in the calling thread for one."""
    if not (isinstance(workers, int) and workers >= 1):
        raise ParamError(f"workers = {workers!r} must be a positive integer")
    return Inline() if workers == 1 else ThreadPoolExecutor(workers, thread_name_prefix="artclass")


@contextmanager
def worker_pool(workers: int) -> Iterator[ThreadPoolExecutor | Inline]:
    """:func:`executor` for the duration of a ``with`` block, shut down after it.

    While ``workers`` > 1 threads of artclass's own run, OpenCV is kept to one thread: the workers
    already keep every core busy, and OpenCV's threads (optical flow, filters) would only contend
    with them. With one worker OpenCV's threads shorten the wall time, so they stay. OpenCV gives the
    same result on any number of threads. It is a process-wide setting, restored afterwards.
    """
    import cv2

    pool = executor(workers)
    before = cv2.getNumThreads()
    if workers > 1:
        cv2.setNumThreads(1)
    try:
        yield pool
    finally:
        cv2.setNumThreads(before)
        pool.shutdown(wait=True, cancel_futures=True)


class Inline:
    """The executor of ``workers=1``: runs each job at once, in the calling thread."""

    def submit(self, fn, *args) -> Future:
        fut: Future = Future()
        try:
            fut.set_result(fn(*args))
        except BaseException as exc:
            fut.set_exception(exc)
        return fut

    def shutdown(self, **_kw) -> None:
        pass


def stream_pairs(
    n: int,
    k: int,
    *,
    frame: Callable[[int, dict], Any],
    finish: Callable[[Any], Any],
    pair: Callable[[Any, tuple, dict], Any],
    done: Callable[[Any, Any], None],
    timing: dict[str, float],
    workers: int = 1,
    reach: int | None = None,
) -> list:
    """Compute ``n`` frames and the pairs (i, i + k), holding only what pending pairs need.

    Parameters
    ----------
    n, k : the number of frames and the frame skip
    frame : ``(i, timing) -> raw frame i`` (run on a worker; adds its stage times to ``timing``)
    finish : ``raw frame -> frame`` (run in the calling thread, in frame order)
    pair : ``(frame_i, frames_after, timing) -> pair`` (run on a worker), where ``frames_after`` are
        frames i + 1 .. i + reach (fewer at the end of the sequence, never fewer than k)
    done : ``(frame_i, pair)`` called in the calling thread as pairs complete, in order
    timing : the jobs' stage timings are added to it (s)
    workers : threads; at most about ``2 * workers + reach`` frames are in flight at once
    reach : how many frames after frame i its pair may use (default, and at least, ``k``)

    Returns
    -------
    list : the finished frames, in order
    """
    reach = max(reach or k, k)
    ahead = 0 if workers == 1 else 2 * workers  # frames read ahead of the one being collected
    frame_jobs: dict[int, Future] = {}
    pair_jobs: deque[tuple[Any, Future]] = deque()
    frames, pending, submitted = [], {}, 0

    def collect(block: bool) -> None:
        while pair_jobs and (block or pair_jobs[0][1].done()):
            first, fut = pair_jobs.popleft()
            job = fut.result()
            merge_timing(timing, job.timing)
            done(first, job.value)
            block = block and len(pair_jobs) > 2 * workers

    with worker_pool(workers) as pool:
        for j in range(n):
            while submitted < min(n, j + ahead + 1):
                frame_jobs[submitted] = pool.submit(_timed, frame, submitted)
                submitted += 1
            job = frame_jobs.pop(j).result()
            merge_timing(timing, job.timing)
            frames.append(fr := finish(job.value))
            pending[j] = fr
            # Pair i starts once frame i + reach is in, or the last frame is.
            for i in range(j - reach, j - k + 1) if j == n - 1 else (j - reach,):
                if i >= 0 and (first := pending.pop(i, None)) is not None:
                    after = tuple(pending[m] for m in range(i + 1, j + 1))
                    pair_jobs.append((first, pool.submit(_timed, pair, first, after)))
            collect(block=len(pair_jobs) > 2 * workers)
        while pair_jobs:
            collect(block=True)
    return frames


def _timed(fn: Callable, *args) -> Job:
    timing: dict[str, float] = {}
    return Job(fn(*args, timing), timing)


def each(fn: Callable, items: list, workers: int = 1) -> list:
    """``fn`` of each item, in order, on ``workers`` threads."""
    with worker_pool(workers) as pool:
        return [f.result() for f in [pool.submit(fn, item) for item in items]]


def merge_timing(timing: dict[str, float], more: dict[str, float]) -> None:
    """Add the stage times (s) of ``more`` to ``timing``."""
    for stage, seconds in more.items():
        add_time(timing, stage, seconds)


def add_time(timing: dict[str, float], stage: str, seconds: float) -> None:
    timing[stage] = timing.get(stage, 0.0) + seconds

"""The evaluation's local worker processes (``sim.evaluation.trials.run_trials``): spawned, one BLAS
thread each, quiet on Ctrl-C, and never outliving the run."""
from __future__ import annotations

import contextlib
import os
import signal


def one_blas_thread() -> None:
    # one BLAS thread per worker: the workers already fill the cores
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(var, "1")


def worker_init() -> None:
    one_blas_thread()
    # Ctrl-C reaches the whole process group: the parent stops the pool, the workers stay quiet
    # (they already start with SIGINT ignored, worker_pool; this covers a replaced worker)
    signal.signal(signal.SIGINT, signal.SIG_IGN)


@contextlib.contextmanager
def worker_pool(ctx, workers: int):
    """A pool of spawned workers that never outlives the block: terminated on leaving it for any
    reason (a worker's error, Ctrl-C, or SIGTERM, which raises SystemExit(143) meanwhile).

    While the pool starts (milliseconds: the workers import on their own afterwards):
    - SIGINT is ignored, a disposition the workers inherit across exec (a signal mask is not:
      spawned children start unblocked), so a Ctrl-C to the process group never kills one
      mid-import; one pressed in that window is lost.
    - SIGTERM is only recorded, and raised once the pool exists, so the pool is terminated rather
      than left half-built with workers orphaned. Recorded by the handler, not held back by a
      mask: this process has other threads (the progress bar's, BLAS's) that a signal sent to
      the process may land on, whatever the main thread blocks.
    Signal handling only from the main thread, where Python allows it."""
    import threading

    main = threading.current_thread() is threading.main_thread()

    def _raise(signum, frame):
        raise SystemExit(128 + signum)

    held: list[int] = []
    old_term = signal.signal(signal.SIGTERM, _raise) if main else None
    pool = None
    try:
        if main:
            old_int = signal.signal(signal.SIGINT, signal.SIG_IGN)
            signal.signal(signal.SIGTERM, lambda signum, frame: held.append(signum))
        try:
            pool = ctx.Pool(workers, initializer=worker_init)
        finally:
            if main:
                signal.signal(signal.SIGINT, old_int)
                signal.signal(signal.SIGTERM, _raise)
        if held:
            _raise(held[0], None)
        yield pool
    finally:
        if pool is not None:
            pool.terminate()
        if main:
            signal.signal(signal.SIGTERM, old_term)

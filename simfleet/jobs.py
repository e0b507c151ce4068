"""Simulation jobs run in order, on worker processes when there are several, with a progress line."""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor

from shared.progress import Progress


def run_jobs(fn: Callable, jobs: Sequence, label: str, workers: int | None = None,
             progress: bool | None = None) -> list:
    """``[fn(job) for job in jobs]``, on up to ``workers`` processes (default: the cores, at most 4).

    The results keep the jobs' order, so what a simulation writes does not depend on the workers.
    """
    workers = workers if workers is not None else min(len(jobs), os.cpu_count() or 1, 4)
    records = []
    with Progress(len(jobs), label, enabled=progress) as bar:
        if workers > 1 and len(jobs) > 1:
            with ProcessPoolExecutor(workers) as pool:
                for rec in pool.map(fn, jobs, chunksize=max(1, len(jobs) // (4 * workers))):
                    records.append(rec)
                    bar.advance()
        else:
            for job in jobs:
                records.append(fn(job))
                bar.advance()
    return records

"""Soft-DTW throughput: our numba all-pairs path vs tslearn, and the batched autograd op.

Prints one JSON line per figure. Timings are the median (and best) of several runs after a warm-up call
(numba JIT / thread-pool start-up excluded), because the machine may be shared.

    .venv/bin/python benchmarks/bench_soft_dtw.py [--n 128] [--t 100] [--d 3] [--gamma 1e-5] [--reps 5]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import time
import warnings
from collections.abc import Callable

import numpy as np
import torch

from lerobot_pdp.benchmark.machine import cpu_model
from lerobot_pdp.soft_dtw import soft_dtw, soft_dtw_cdist


def _time(fn: Callable[[], object], reps: int) -> tuple[float, float, float]:
    """(median wall s, best wall s, median process CPU s). CPU time (all threads) shows the work done
    independently of other load on a shared machine; wall time is what a user waits."""
    ts, cs = [], []
    for _ in range(reps):
        c0, t0 = time.process_time(), time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
        cs.append(time.process_time() - c0)
    return statistics.median(ts), min(ts), statistics.median(cs)


def _emit(**kw: object) -> None:
    print(json.dumps({**kw, "cpu": cpu_model()}), flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=128, help="number of sequences (all pairs)")
    ap.add_argument("--t", type=int, default=100, help="sequence length")
    ap.add_argument("--d", type=int, default=3, help="feature dim")
    ap.add_argument("--gamma", type=float, default=1e-5)
    ap.add_argument("--reps", type=int, default=5)
    ap.add_argument("--batch", type=int, default=64, help="pairs in the batched autograd benchmark")
    ap.add_argument("--skip-tslearn", action="store_true")
    args = ap.parse_args()

    threads = os.cpu_count() or 1
    rng = np.random.default_rng(0)
    # Smooth random-walk trajectories: closer to behaviour traces than white noise (more near-ties).
    X = np.cumsum(rng.normal(size=(args.n, args.t, args.d)), axis=1) * 0.1
    pairs = args.n * (args.n + 1) // 2  # both implementations compute the upper triangle incl. diagonal
    cells = pairs * args.t * args.t
    common = {"n": args.n, "T": args.t, "d": args.d, "gamma": args.gamma, "pairs": pairs, "cells": cells}

    soft_dtw_cdist(X[:4], args.gamma)  # JIT / cache load + thread pool start
    ours = soft_dtw_cdist(X, args.gamma)
    med, best, cpu = _time(lambda: soft_dtw_cdist(X, args.gamma), args.reps)
    _emit(
        bench="soft_dtw_cdist",
        impl="lerobot_pdp",
        threads=threads,
        seconds=med,
        best_seconds=best,
        cells_per_s=cells / med,
        best_cells_per_s=cells / best,
        cells_per_cpu_s=cells / cpu,
        loadavg_1min=os.getloadavg()[0],
        **common,
    )

    if not args.skip_tslearn:
        from tslearn.metrics import cdist_soft_dtw

        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            cdist_soft_dtw(X[:4], gamma=args.gamma, n_jobs=threads)  # warm up its numba kernels
            theirs = cdist_soft_dtw(X, gamma=args.gamma, n_jobs=threads)
            t_med, t_best, t_cpu = _time(
                lambda: cdist_soft_dtw(X, gamma=args.gamma, n_jobs=threads), max(1, min(args.reps, 3))
            )
        _emit(
            bench="soft_dtw_cdist",
            impl="tslearn",
            n_jobs=threads,
            seconds=t_med,
            best_seconds=t_best,
            cells_per_s=cells / t_med,
            best_cells_per_s=cells / t_best,
            cells_per_cpu_s=cells / t_cpu,
            loadavg_1min=os.getloadavg()[0],
            max_abs_diff_vs_ours=float(np.abs(np.asarray(theirs) - ours).max()),
            **common,
        )
        _emit(
            bench="soft_dtw_cdist",
            impl="ratio_ours_over_tslearn",
            speedup=t_med / med,
            speedup_best=t_best / best,
            speedup_cpu=t_cpu / cpu,
            **common,
        )

    # Batched differentiable op: forward + backward for B pairs.
    B = args.batch
    xs = torch.tensor(X[:B] if args.n >= B else rng.normal(size=(B, args.t, args.d)))
    ys = torch.tensor(np.roll(xs.numpy(), 1, axis=0) + 0.05)
    for backend, dtype in (("numba", torch.float64), ("numba", torch.float32), ("torch", torch.float64)):
        x = xs.to(dtype).requires_grad_(True)
        y = ys.to(dtype).requires_grad_(True)

        def step(x: torch.Tensor = x, y: torch.Tensor = y, backend: str = backend) -> None:
            soft_dtw(x, y, args.gamma, backend=backend).sum().backward()

        step()
        med, best, cpu = _time(step, 4 * args.reps if backend == "numba" else max(1, min(args.reps, 3)))
        bcells = B * args.t * args.t
        _emit(
            bench="soft_dtw_fwd_bwd",
            impl=f"lerobot_pdp/{backend}",
            dtype=str(dtype).removeprefix("torch."),
            B=B,
            T=args.t,
            d=args.d,
            gamma=args.gamma,
            seconds=med,
            best_seconds=best,
            cells_per_s=bcells / med,
            cpu_seconds=cpu,
            torch_threads=torch.get_num_threads(),
        )


if __name__ == "__main__":
    main()

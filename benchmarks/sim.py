"""Speed of the can world: throws per second per core, and the full data set's wall time.

    python benchmarks/sim.py                 # sample of 1000 data-set rows, one core
    python benchmarks/sim.py --full          # generate the whole data set, timed

The sample draws rows of the full data set (every stable configuration x 195 fields x
3 angles x 3 repeats) uniformly at random, so its rate, divided into the data set's
size and the number of cores, estimates the full run's wall time. Unthrowable rows cost
nothing (they are not simulated); "simulated throws per second" counts the others.
Target (issue 3): the whole data set in under 15 minutes on 2 cores.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

import numpy as np

from sim2d import can_dataset, materials
from sim2d.configurations import stable_configurations


def sample_rate(n: int, seed: int) -> tuple[float, float, int]:
    """Rows per second and simulated throws per second on this core, and the row count."""
    configs = np.array(stable_configurations())
    rows = can_dataset._rows(configs, [0, 1, 2], 3)
    picked = rows[np.random.default_rng(seed).choice(len(rows), size=n, replace=False)]
    start = time.perf_counter()
    result = can_dataset._simulate_chunk(picked, jitter=0.003, seed=0)
    elapsed = time.perf_counter() - start
    simulated = int(result["throwable"].sum())
    return n / elapsed, simulated / elapsed, len(rows)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--throws", type=int, default=1000, help="sample size (rows)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--full", action="store_true", help="generate the full data set")
    parser.add_argument("--out", type=Path, default=None, help="where --full writes")
    args = parser.parse_args(argv)

    cores = os.cpu_count() or 1
    start = time.perf_counter()
    stable = stable_configurations()
    print(f"{len(stable)} stable configurations ({time.perf_counter() - start:.1f} s, cached)")
    rows_per_s, throws_per_s, total = sample_rate(args.throws, args.seed)
    print(f"one core: {rows_per_s:.0f} data-set rows/s, {throws_per_s:.0f} simulated throws/s")
    estimate = total / (rows_per_s * cores)
    print(f"full data set: {total} rows; estimated wall time on {cores} cores: {estimate:.0f} s")
    if args.full:
        with tempfile.TemporaryDirectory() as tmp:
            out = args.out or Path(tmp) / "can_dataset.npz"
            start = time.perf_counter()
            can_dataset.generate_dataset(out)
            wall = time.perf_counter() - start
            data = can_dataset.load_dataset(out)
            print(
                f"full data set measured: {len(data)} rows in {wall:.0f} s on {cores} cores "
                f"({len(data) / wall / cores:.0f} rows/s per core); "
                f"{int(data.timed_out.sum())} timed out, "
                f"{int((~data.throwable).sum())} unthrowable rows; written to {out}"
            )
    print(f"time step {materials.TIME_STEP} s, cap {materials.MAX_SIM_TIME} s")


if __name__ == "__main__":
    main()

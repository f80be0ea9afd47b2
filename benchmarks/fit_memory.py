"""Peak memory of fitting a data set ten times the can data set: in chunks vs in one pass.

    .venv/bin/python benchmarks/fit_memory.py [--copies 10] [--threads 1]

The can network (Fig. 2: 107 configurations, 11 counts, 195 fields) is fitted on
``copies`` x 187,785 synthetic rows (the can data set's size), drawn at random in
chunks of one data set each. "one pass" builds every row first, then fits; "chunks"
hands ``fit`` a generator, so one chunk is in memory at a time and only the summed
statistics stay. Each mode runs in a fresh process, whose peak resident memory
(``ru_maxrss``) is reported beside that of a process that fits one chunk alone: the
network's own tables (the end configuration's is 107 x 11 x 195 x 107 cells, 196 MiB)
cost the same in every mode, so what grows with the data is the peak above that one.
Both modes must give the same tables (checked).

Goal: the chunked fit's peak stays at the one-chunk fit's whatever
the number of rows; the one-pass fit's grows with them.
"""

from __future__ import annotations

import argparse
import json
import platform
import resource
import subprocess
import sys
import time
from pathlib import Path

from timing import add_out, print_also_to  # benchmarks/timing.py, beside this script

ROWS_PER_DATA_SET = 187_785
N_CONFIGS = 107


def chunk(net, index: int):
    """One data set's worth of random rows (seeded by ``index``), encoded."""
    import numpy as np
    from effect_networks.models.can_pyramid import can_rows

    rng = np.random.default_rng(index)
    states = np.asarray(net.feature("config").states)
    start = states[rng.integers(0, len(states), ROWS_PER_DATA_SET)]
    end = start & states[rng.integers(0, len(states), ROWS_PER_DATA_SET)]
    end = np.where(np.isin(end, states), end, start)
    field = rng.integers(0, len(net.actions), ROWS_PER_DATA_SET)
    return can_rows(net, start, field, end)


def run(mode: str, copies: int, threads: int) -> dict:
    import torch
    from effect_networks.inference import fit
    from effect_networks.models.can_pyramid import can_network

    torch.set_num_threads(threads)
    net = can_network(range(N_CONFIGS))
    start = time.perf_counter()
    if mode == "baseline":
        fit(net, chunk(net, 0))
        digest, held = None, 0
    else:
        if mode == "chunks":
            params = fit(net, (chunk(net, i) for i in range(copies))).params
        else:
            parts = [chunk(net, i) for i in range(copies)]
            rows = parts[0]
            rows = type(rows)(
                net, {k: torch.cat([p[k] for p in parts]) for k in rows}, rows.n_rows * copies
            )
            del parts
            params = fit(net, rows).params
        digest = float(sum(c.n.sum() for c in params.cpds.values()))
        one = chunk(net, 0)
        held = sum(v.nbytes for v in one.values()) * (1 if mode == "chunks" else copies)
        torch.save(params.cpds["end.config"].probs, f"/tmp/fit_memory_{mode}.pt")
    seconds = time.perf_counter() - start
    peak_mib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    return {
        "mode": mode,
        "seconds": seconds,
        "peak_mib": peak_mib,
        "digest": digest,
        "rows_mib": held / 2**20,
    }


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--copies", type=int, default=10)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--child", choices=["baseline", "chunks", "one-pass"])
    add_out(parser)
    args = parser.parse_args(argv)
    print_also_to(args.out, __file__)
    if args.copies < 1 or args.threads < 1:
        parser.error("--copies and --threads must be positive")
    if args.child:
        print(json.dumps(run(args.child, args.copies, args.threads)))
        return {}
    root = Path(__file__).resolve().parents[1]
    out = {}
    for mode in ("baseline", "chunks", "one-pass"):
        cmd = [sys.executable, __file__, "--child", mode, "--copies", str(args.copies)]
        cmd += ["--threads", str(args.threads)]
        done = subprocess.run(cmd, cwd=root, capture_output=True, text=True, check=True)
        out[mode] = json.loads(done.stdout.strip().splitlines()[-1])
    import torch

    same = torch.equal(
        torch.load("/tmp/fit_memory_chunks.pt"), torch.load("/tmp/fit_memory_one-pass.pt")
    )
    rows = args.copies * ROWS_PER_DATA_SET
    print(f"machine: {platform.machine()}, torch {torch.__version__}, threads {args.threads}")
    print(f"can network, {rows:,} rows ({args.copies} x the can data set), one chunk = 1 data set")
    print(f"{'what':<40}{'peak MiB':>10}{'seconds':>10}")
    for mode in ("baseline", "chunks", "one-pass"):
        name = {
            "baseline": "fit of one chunk (1 data set)",
            "chunks": "fit in chunks (generator)",
            "one-pass": "fit in one pass (all rows)",
        }[mode]
        print(f"{name:<40}{out[mode]['peak_mib']:>10.0f}{out[mode]['seconds']:>10.1f}")
    base = out["baseline"]["peak_mib"]
    print(
        f"above the one-chunk fit: chunks {out['chunks']['peak_mib'] - base:.0f} MiB, "
        f"one pass {out['one-pass']['peak_mib'] - base:.0f} MiB "
        "(goal: chunks near 0 at any size; one pass grows with the rows)"
    )
    print(
        f"encoded rows held at once: chunks {out['chunks']['rows_mib']:.0f} MiB, "
        f"one pass {out['one-pass']['rows_mib']:.0f} MiB"
    )
    print(f"tables equal bit for bit: {same}")
    return out


if __name__ == "__main__":
    main()

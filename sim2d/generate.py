"""Generate the can data set from the command line, on any executor.

    python -m effect_networks.sim2d.generate data/can_dataset.npz                       # every core here
    python -m effect_networks.sim2d.generate data/can_dataset.npz --executor dask-local:8
    python -m effect_networks.sim2d.generate data/can_dataset.npz --executor dask://scheduler:8786
    python -m effect_networks.sim2d.generate data/can_dataset.npz --executor ray
    python -m effect_networks.sim2d.generate small.npz --configs 15 1023 --angles 0 --repeats 1

Defaults give the full data set (every stable configuration x 195 fields x 3 angles x 3
repeats). An interrupted run resumes where it stopped when started again with the same
arguments; see :func:`sim2d.can_dataset.generate_dataset`. A full disk or a read-only
folder ends the run with a two-line message (exit status 1), a bad argument or an
unreachable cluster with a usage error (2).
"""

from __future__ import annotations

import argparse
import sys
import time

from effect_networks.sim2d.can_dataset import generate_dataset, load_dataset
from effect_networks.sim2d.chunks import write_failure
from effect_networks.sim2d.executors import default_spec, parse_spec

__all__ = ["main"]


def _executor(text: str) -> str:
    try:
        parse_spec(text)
    except ValueError as error:
        raise argparse.ArgumentTypeError(str(error)) from None
    return text


def main(argv=None) -> int:
    """Run the command line; returns the exit status."""
    parser = argparse.ArgumentParser(
        prog="python -m effect_networks.sim2d.generate",
        description=__doc__.splitlines()[0],
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="\n".join(__doc__.splitlines()[2:8]),
    )
    parser.add_argument("path", help="output .npz")
    parser.add_argument(
        "--executor",
        type=_executor,
        default=None,
        help=f"process:N | dask-local:N | dask://HOST:PORT | ray (default {default_spec()})",
    )
    parser.add_argument("--configs", type=int, nargs="+", help="start masks (default: all stable)")
    parser.add_argument("--angles", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--jitter", type=float, default=0.003, help="aim error sd, metres")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--chunk-size", type=int, default=1000, help="throws per chunk")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    args = parser.parse_args(argv)
    start = time.perf_counter()
    try:
        path = generate_dataset(
            args.path,
            configs=args.configs,
            angles=args.angles,
            repeats=args.repeats,
            jitter=args.jitter,
            seed=args.seed,
            executor=args.executor,
            chunk_size=args.chunk_size,
            progress=not args.quiet,
        )
    except (ValueError, RuntimeError) as error:
        parser.exit(2, f"{parser.prog}: error: {error}\n")
    except KeyboardInterrupt:
        parser.exit(130, f"{parser.prog}: interrupted; run it again to resume\n")
    except OSError as error:
        failure = write_failure(error)
        if failure is None:
            raise
        parser.exit(
            1,
            f"{parser.prog}: error: {failure}\n{parser.prog}: the chunks finished so far "
            "are kept; free some space or choose a writable folder, then run it again to "
            "resume\n",
        )
    rows = len(load_dataset(path))
    print(f"{path}: {rows} throws in {time.perf_counter() - start:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())

r"""Every goal the physics can reach: the combined system beside the physics bound.

For each table height, the robot throws at every height of the pyramid's face from every
state it can reach (its experience, and fresh repeats for the bound); the can network is
trained on that experience with aim heights as actions, the throw network on random
throws; the exact planner and the paper's round planner are played towards every stable
sub-configuration that the bound reaches within ``--horizon`` throws
(:mod:`experiments.all_goals`).

    python examples/all_goals.py [--quick] [--table-z 0.75 0.35] [--executor process:N]

Writes all_goals.json, all_goals.md and all_goals.png to ``--out``.
"""

from __future__ import annotations

import argparse

import torch

from experiments.all_goals import AllGoalsConfig, AllGoalsResult, run_all_goals
from experiments.config import config_or_exit, run_script

QUICK = dict(step=0.01, train_repeats=2, bound_repeats=4, episodes=10, n_throws=5000, bins=8)
SIZED = ("step", "train_repeats", "bound_repeats", "episodes", "n_throws", "bins")


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    d = AllGoalsConfig()
    parser.add_argument("--quick", action="store_true", help=f"smaller settings: {QUICK}")
    parser.add_argument("--data-dir", default=str(d.data_dir))
    parser.add_argument("--out", default="results")
    parser.add_argument("--table-z", type=float, nargs="+", default=list(d.table_z))
    parser.add_argument("--step", type=float, help=f"m between aim heights ({d.step})")
    parser.add_argument("--train-repeats", type=int, help=f"per height ({d.train_repeats})")
    parser.add_argument("--bound-repeats", type=int, help=f"even ({d.bound_repeats})")
    parser.add_argument("--horizon", type=int, default=d.horizon, help="throws per goal")
    parser.add_argument("--episodes", type=int, help=f"plays per goal ({d.episodes})")
    parser.add_argument("--n-throws", type=int, help=f"throw network's data ({d.n_throws})")
    parser.add_argument("--bins", type=int, help=f"throw clusters per axis ({d.bins})")
    parser.add_argument("--jitter", type=float, default=d.jitter, help="aim jitter, m")
    parser.add_argument("--noise", action="store_true", help="throw with release noise")
    parser.add_argument("--executor", help="process:N | dask-local:N | dask://HOST:PORT | ray")
    parser.add_argument("--seed", type=int, default=d.seed)
    parser.add_argument("--quiet", action="store_true")
    args = parser.parse_args(argv)
    sized = dict(QUICK) if args.quick else {}
    sized |= {k: getattr(args, k) for k in SIZED if getattr(args, k) is not None}
    args.config = config_or_exit(
        parser,
        lambda: AllGoalsConfig(
            data_dir=args.data_dir,
            table_z=tuple(args.table_z),
            horizon=args.horizon,
            jitter=args.jitter,
            noise=args.noise,
            executor=args.executor,
            seed=args.seed,
            progress=not args.quiet,
            **sized,
        ),  # fmt: skip
    )
    return args


def main(args: argparse.Namespace) -> AllGoalsResult:
    torch.set_num_threads(1)
    result = run_all_goals(args.config)
    result.save(args.out)
    print(result.to_markdown())
    return result


if __name__ == "__main__":
    run_script(main, parse_args())

r"""What the physics allows: upper bounds on Table I and on the combined scenarios.

A learned model can at best pick the action that the simulator itself shows to work most
often. This script measures that best, with no learning at all, so the experiments' goals
can be read against it:

* **Table I.** Every 0° field is thrown ``--repeats`` more times from every start (the data
  set's jitter, fresh seeds; :func:`sim2d.can_dataset.generate_dataset`). For each Table I
  case the field is chosen by its success on the first half of the repeats and scored on
  the second half (held out, so that luck in the choice does not count).
* **Combined.** From every state between the full pyramid and each scenario's goal, the
  robot throws at every reachable height of the pyramid's face (exact inverse kinematics,
  ``--step`` apart) ``--combined-repeats`` times with the data set's jitter
  (:mod:`sim2d.combined`). The best policy over ``--horizon`` throws is planned on half the
  repeats and scored on the other half (:func:`inference.planning.policy_value`).

    python examples/physics_bounds.py [--scale full|quick|tiny] [--table-z 0.75 0.35 ...]
        [--executor process:N | dask-local:N | dask://HOST:PORT | ray]

Both bounds' simulations are saved under ``--data-dir`` as they finish and resumed when
interrupted.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from can_common import SCALES, can_dataset, start_configurations  # noqa: E402
from can_tossing import ANGLE, table_one_cases  # noqa: E402
from combined import SCENARIOS  # noqa: E402

from inference.planning import exact_plan, policy_value  # noqa: E402
from sim2d import field_throws, geometry, materials  # noqa: E402
from sim2d.can_dataset import generate_dataset, load_dataset  # noqa: E402
from sim2d.chunks import locked, read_npz, run_chunks  # noqa: E402
from sim2d.combined import TABLE_TOP_Z, throws_from  # noqa: E402
from sim2d.configurations import stable_configurations  # noqa: E402
from sim2d.executors import open_executor, parse_spec  # noqa: E402

BOUND_SEED = 1  # the training data set uses seed 0: these throws are fresh


def held_out_best(success: np.ndarray) -> np.ndarray:
    """``success (cases, actions, repeats)`` bool -> per case, the held-out rate of the action
    that succeeded most often on the first half of the repeats (ties: the lowest index)."""
    half = success.shape[-1] // 2
    chosen = success[..., :half].mean(-1).argmax(-1)
    held = success[..., half:].mean(-1)
    return np.take_along_axis(held, chosen[:, None], -1)[:, 0]


def table_one_bound(args, executor=None) -> dict:
    """Table I's cases scored with the simulator's own best field."""
    data = can_dataset(Path(args.data_dir), args.scale, progress=not args.quiet, executor=executor)
    start, desired = table_one_cases(data, "counts")
    configs = [c for c in start_configurations(SCALES[args.scale]["n_configs"]) if c]
    path = generate_dataset(
        Path(args.data_dir) / f"can_bound_{args.scale}_{args.repeats}.npz",
        configs=configs,
        angles=(ANGLE,),
        repeats=args.repeats,
        seed=BOUND_SEED,
        executor=executor,
        progress=not args.quiet,
    )
    sims = load_dataset(path)
    fields = np.flatnonzero([field_throws.is_throwable(f, ANGLE) for f in range(geometry.N_FIELDS)])
    order = np.lexsort((sims.repeat, sims.field, sims.start_config))
    counts = sims.count_after[order].reshape(len(configs), geometry.N_FIELDS, args.repeats)
    counts = counts[:, fields]  # (configs, throwable fields, repeats)
    row = {c: i for i, c in enumerate(sorted(configs))}
    success = counts[[row[int(s)] for s in start]] == desired[:, None, None]
    bound = held_out_best(success)
    return {
        "n_cases": int(len(start)),
        "repeats": args.repeats,
        "exact_fraction_bound": float(bound.mean()),
        "exact_fraction_in_sample": float(success.mean(-1).max(-1).mean()),
        "n_cases_never_reached": int((~success.any((1, 2))).sum()),
    }


def combined_outcomes(args, table_z: float, jitter: float, states, executor) -> dict:
    """``{state: (heights, repeats) next states}``, saved per state under ``--data-dir``
    (resumable; :func:`sim2d.chunks.run_chunks`)."""
    states = sorted(states)
    tasks = [(s, table_z, args.step, args.combined_repeats, jitter, BOUND_SEED) for s in states]
    protocol = {
        "producer": "sim2d.combined.throws_from",
        "tasks": [list(t) for t in tasks],
        "constants": materials.physical_constants(),
    }
    name = f"combined_bound_{args.scale}_{table_z}_{args.step}_{args.combined_repeats}.parts"
    folder = Path(args.data_dir) / name
    with locked(folder):
        files = run_chunks(
            folder, protocol, throws_from, tasks, executor=executor,
            progress=not args.quiet, desc=f"combined bound (table {table_z} m)",
        )  # fmt: skip
        return {s: read_npz(f)["next_states"] for s, f in zip(states, files, strict=True)}


def combined_bound(args, table_z: float, jitter: float, executor=None) -> dict:
    """Per scenario: the best plan's held-out success, over the robot's exact throws."""
    stable = stable_configurations()
    goals = {
        name: geometry.FULL_PYRAMID & ~geometry.cans_to_mask(removed)
        for name, removed in SCENARIOS.items()
    }
    needed = {s for goal in goals.values() for s in stable if s & goal == goal}
    by_state = combined_outcomes(args, table_z, jitter, needed, executor)
    out = {}
    for name, goal in goals.items():
        states = sorted(s for s in stable if s & goal == goal)
        outcomes = [by_state[s] for s in states]
        index = {s: i for i, s in enumerate(states)}
        half = args.combined_repeats // 2
        t = [torch.zeros(len(states), outcomes[0].shape[0], len(states), dtype=torch.float64)]
        t.append(t[0].clone())  # (planned on, scored on)
        for i, o in enumerate(outcomes):
            for part, cols in ((0, slice(None, half)), (1, slice(half, None))):
                for a, row in enumerate(o[:, cols]):
                    for nxt in row:  # a next state outside the goal's supersets is a failure
                        if nxt in index:
                            t[part][i, a, index[nxt]] += 1.0 / len(row)
        plan = exact_plan(t[0], index[goal], args.horizon)
        value = policy_value(t[1], plan.policy, index[goal], args.horizon)
        full = index[geometry.FULL_PYRAMID]
        out[name] = {
            "success_bound": float(value[args.horizon, full]),
            "success_in_sample": float(plan.value[args.horizon, full]),
            "one_throw_bound": float(value[1, full]),
            "n_states": len(states),
            "n_heights": int(outcomes[0].shape[0]),
        }
    return out


def markdown(result: dict) -> str:
    t = result["table_one"]
    lines = [
        f"**Table I, best field found by simulation** ({t['repeats']} jittered repeats per "
        f"field, chosen on half, scored on the other half): {100 * t['exact_fraction_bound']:.2f} % "
        f"exact of {t['n_cases']} cases (in-sample {100 * t['exact_fraction_in_sample']:.2f} %); "
        f"{t['n_cases_never_reached']} cases no repeat reached.",
        "",
        "**Combined, best plan over the robot's exact throws** (held-out success within "
        f"{result['horizon']} throws; in one throw):",
        "",
        "| table top (m) | " + " | ".join(SCENARIOS) + " |",
        "|---" * (len(SCENARIOS) + 1) + "|",
    ]
    for table_z, scen in result["combined"].items():
        cells = [
            f"{100 * s['success_bound']:.1f} % ({100 * s['one_throw_bound']:.1f} %)"
            for s in scen.values()
        ]
        lines.append(f"| {table_z} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def main(args: argparse.Namespace) -> dict:
    torch.set_num_threads(1)
    started = time.perf_counter()
    with open_executor(args.executor) as executor:
        data = can_dataset(Path(args.data_dir), args.scale, progress=False, executor=executor)
        jitter = float(data.metadata["jitter"])
        result = {
            "scale": args.scale,
            "table_one": table_one_bound(args, executor),
            "horizon": args.horizon,
            "jitter": jitter,
            "combined": {str(z): combined_bound(args, z, jitter, executor) for z in args.table_z},
        }
    result["seconds"] = time.perf_counter() - started
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "physics_bounds.json").write_text(json.dumps(result, indent=2))
    (out / "physics_bounds.md").write_text(markdown(result))
    print(markdown(result))
    return result


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--scale", choices=tuple(SCALES), default="full")
    parser.add_argument("--data-dir", default="data")
    parser.add_argument("--out", default="results")
    parser.add_argument("--repeats", type=int, default=16, help="Table I: throws per field")
    parser.add_argument("--table-z", type=float, nargs="+", default=[TABLE_TOP_Z])
    parser.add_argument("--step", type=float, default=0.002, help="combined: m between heights")
    parser.add_argument("--combined-repeats", type=int, default=8, help="combined: per height")
    parser.add_argument("--horizon", type=int, default=6, help="combined: throws allowed")
    parser.add_argument(
        "--executor",
        default=None,
        help="process:N | dask-local:N | dask://HOST:PORT | ray (default: every core here)",
    )
    parser.add_argument("--quiet", action="store_true")
    args = parser.parse_args(argv)
    if args.executor is not None:
        try:
            parse_spec(args.executor)
        except ValueError as error:
            parser.error(str(error))
    if args.repeats < 2 or args.combined_repeats < 2:
        parser.error(
            "--repeats and --combined-repeats must be at least 2 (half choose, half score)"
        )
    return args


if __name__ == "__main__":
    main(parse_args())

"""The paper's §III illustration: a "remove" action and a "tap" action with a force.

Rudolph, Mühlig, Gienger, Böhme, "Learning the Consequences of Actions: Representing
Effects as Feature Changes", §III. Two small worlds:

* remove: a feature ``visible`` (False/True); "remove" makes a visible object invisible,
  "look" changes nothing. Two well-separated outcomes: the plain network does fine.
* tap: a ball at ``position`` (m) is tapped with a force F uniform on [0, 20] N and rolls
  ``0.02 F + 0.0015 F^2`` m (rolling friction makes the mapping non-linear). Without a
  parameter site the network can only predict the average roll; with the parameter site
  (``param.force``) and its equidistant clusters (a mixture of Gaussians) it follows F.

Prints the prediction error of each variant and writes ``tap_and_remove.png``::

    .venv/bin/python examples/tap_and_remove.py --n 2000 --out results/tap_and_remove
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

from inference import fit, imitation_check, infer_action, predict
from models import Continuous, Discrete, EffectNetwork, Parameter

FORCE = (0.0, 20.0)  # N


def roll(force: np.ndarray) -> np.ndarray:
    """Distance rolled (m) for a tap of ``force`` (N): the hidden law the network learns."""
    return 0.02 * force + 0.0015 * force**2


def get_data(n: int, seed: int) -> dict[str, np.ndarray]:
    """``n`` random taps and removes: arrays of shape ``(n,)``, position in metres, force in N."""
    rng = np.random.default_rng(seed)
    visible = rng.random(n) < 0.7
    action = np.array(["look", "remove"])[rng.integers(0, 2, n)]
    gone = (action == "remove") & visible & (rng.random(n) < 0.97)
    position = rng.uniform(-1.0, 1.0, n)
    force = rng.uniform(*FORCE, n)
    rolled = position + roll(force) + rng.normal(0.0, 0.01, n)
    return {
        "visible": visible,
        "action": action,
        "visible_after": visible & ~gone,
        "position": position,
        "force": force,
        "rolled": rolled,
    }


def tap_network(bins: int | None) -> EffectNetwork:
    """The tap world with a force parameter cut into ``bins`` clusters, or without one."""
    params = (
        ()
        if bins is None
        else (Parameter("force", FORCE[0], FORCE[1], bins, ("tap",), "position"),)
    )
    return EffectNetwork((Continuous("position", 1),), ("tap",), params)


def tap_rows(d: dict[str, np.ndarray], with_force: bool) -> dict[str, object]:
    rows = {
        "initial.position": d["position"][:, None],
        "action": ["tap"] * len(d["position"]),
        "end.position": d["rolled"][:, None],
    }
    if with_force:
        rows["param.force"] = d["force"][:, None]
    return rows


def main(args: argparse.Namespace) -> dict[str, float]:
    train, test = get_data(args.n, args.seed), get_data(max(args.n // 4, 50), args.seed + 1)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)

    # remove: emulate (which action made it vanish?) and imitate (did "remove" work?)
    remove = EffectNetwork((Discrete("visible", (False, True)),), ("look", "remove"))
    rows = {
        "initial.visible": train["visible"],
        "action": train["action"],
        "end.visible": train["visible_after"],
    }
    remove_params = fit(remove, rows).params
    emulated = infer_action(
        remove, remove_params, {"initial.visible": [True], "end.visible": [False]}
    )
    check = imitation_check(
        remove,
        remove_params,
        {
            "initial.visible": [True, True],
            "action": ["remove", "remove"],
            "end.visible": [False, True],
        },
    )
    print(
        f"remove: object vanished -> best action {emulated.best_names[0]!r} (p = {emulated.probs[0].max():.3f})"
    )
    print(
        f"remove: surprise of 'vanished' {check.surprise[0]:.3f}, of 'still there' {check.surprise[1]:.3f}"
    )

    # tap: predict the end position with and without the force parameter
    truth = test["rolled"]
    results = {}
    predictions = {}
    for label, bins in (
        ("no parameter site", None),
        ("parameter, 1 cluster", 1),
        (f"parameter, {args.bins} clusters", args.bins),
    ):
        net = tap_network(bins)
        params = fit(net, tap_rows(train, bins is not None)).params
        ev = tap_rows(test, bins is not None)
        del ev["end.position"]
        mean = predict(net, params, ev).continuous["position"].mean[:, 0].numpy()
        predictions[label] = mean
        results[label] = float(np.sqrt(np.mean((mean - truth) ** 2)))
        print(f"tap: {label:<26} RMS prediction error {results[label]:.4f} m")
    (out / "tap_and_remove.json").write_text(
        json.dumps({"rms_m": results, "n_train": args.n}, indent=2)
    )
    plot(test, predictions, out / "tap_and_remove.png")
    return results


def plot(test, predictions, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.5, 4.2))
    order = np.argsort(test["force"])
    ax.plot(
        test["force"][order],
        (test["rolled"] - test["position"])[order],
        ".",
        ms=3,
        color="0.6",
        label="observed roll",
    )
    for label, mean in predictions.items():
        ax.plot(
            test["force"][order],
            (mean - test["position"])[order],
            lw=1.8,
            label=f"predicted: {label}",
        )
    ax.set_xlabel("tap force F (N)")
    ax.set_ylabel("end position - initial position (m)")
    ax.set_title("Tap: predicting the effect with and without the force parameter")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--n", type=int, default=2000, help="training rows")
    parser.add_argument("--bins", type=int, default=8, help="force clusters")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default="results/tap_and_remove")
    return parser.parse_args(argv)


if __name__ == "__main__":
    torch.set_num_threads(1)
    main(parse_args())

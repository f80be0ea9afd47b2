"""Throwing (the paper's §IV-B): learn where to aim to hit a point, and re-throw.

A humanoid throws at target points on a wall 2 m away; its joint limits and gravity make
the target-to-hit mapping non-linear. The throw network (:mod:`models.humanoid_throw`)
learns the joint of target and hit as a mixture of Gaussians over an equidistant grid of
target clusters; the inverse query (best cluster by enumeration, then Gaussian
conditioning) answers "where to aim to hit this point". Every test sample's hit is the
evidence; the robot throws at the inferred target (:func:`sim2d.analytic_throw.throw`) and the RMS
error of the new hit against the desired one is reported per axis. The paper's "x" and
"y" on the wall are our ``y`` (lateral) and ``z`` (height).

Data (:func:`get_data`): ``n_train + n_test`` targets uniform on the 2 m x 2 m area and
their hits, both ``(n, 2)`` ``[y, z]`` in metres. The number of clusters per axis is
chosen among ``bins`` by the re-throw error on a validation split of the training set.
Inferred targets are clipped into the target area (the robot cannot aim outside it); test
hits outside the region any noise-free throw reaches (only noisy ones) are kept in the
RMS: the clipped aim is thrown like every other and its error counts. Three fits are
measured: the chosen grid and a single Gaussian without release noise, and the chosen
grid on throws with release noise, beside the noise's own scatter (the same aims thrown
with and without noise), which no inverse can beat.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import ClassVar

import numpy as np
from effect_networks.experiments.harness.config import ConfigError, Result, check_int
from effect_networks.experiments.harness.registry import Experiment
from effect_networks.inference import fit, infer_parameter
from effect_networks.models.humanoid_throw import TARGET, hit_evidence, throw_data, throw_network
from effect_networks.sim2d.analytic_throw import (
    TARGET_AREA,
    ReleaseNoise,
    is_reachable_hit,
    reachable_hit_boundary,
    sample_targets,
    throw,
)
from tqdm.auto import tqdm

__all__ = [
    "QUICK",
    "ThrowingConfig",
    "ThrowingResult",
    "fit_throws",
    "get_data",
    "plot_errors",
    "rethrow",
    "run_throwing",
    "select_bins",
]

PAPER_RMS_M = {"y": 0.0178, "z": 0.0305}  # the paper's "x" and "y" on the wall
GOAL_RMS_M = 0.010
BIN_CANDIDATES = (4, 6, 8, 10, 12, 14, 16, 20)
HIT_MARGIN_M = 0.05  # hits answered up to this far outside the training hits' box
MAX_BINS = 50  # clusters per axis: 2,500 clusters, far more than the throws resolve
#: A first look in seconds.
QUICK = {"n_train": 1_500, "n_test": 200, "bins": (2, 4, 6)}


@dataclass(frozen=True)
class ThrowingConfig:
    """Settings of :func:`run_throwing`; every field is checked on construction.

    Attributes
    ----------
    n_train, n_test : int
        Training throws (of which a fifth validate the grid size) and test hits.
    seed : int
        Seeds the targets and the release noise (>= 0).
    bins : tuple of int
        Grid sizes (clusters per axis) to choose among, each in ``1..MAX_BINS``.
    progress : bool
        Progress bars.
    """

    n_train: int = 29_000
    n_test: int = 1_000
    seed: int = 0
    bins: tuple[int, ...] = BIN_CANDIDATES
    progress: bool = True

    def __post_init__(self):
        check_int("n_train", self.n_train, 10)
        check_int("n_test", self.n_test, 1)
        check_int("seed", self.seed, 0)
        object.__setattr__(self, "bins", tuple(self.bins))
        if not self.bins:
            raise ConfigError("bins", "no grid size given; expected at least one")
        for k in self.bins:
            check_int("bins", k, 1, MAX_BINS)


def get_data(n: int, rng: np.random.Generator, noise: ReleaseNoise | None):
    """``n`` uniform targets ``(n, 2)`` and their hits ``(n, 2)``, ``[y, z]`` in metres."""
    targets = sample_targets(n, rng)
    return targets, throw(targets, rng=rng, noise=noise).hit


def fit_throws(bins, targets, hits):
    """Declaration and fitted parameters of the throw network with ``bins`` clusters."""
    net = throw_network(bins)
    window = (hits.min(0) - HIT_MARGIN_M, hits.max(0) + HIT_MARGIN_M)
    return net, fit(net, throw_data(net, targets, hits)).params, window


def rethrow(model, desired, rng, noise):
    """Infer the aim for each desired hit ``(n, 2)``, throw at it; aims, new hits, clipped."""
    net, params, (low, high) = model
    aim = infer_parameter(net, params, TARGET, hit_evidence(desired, low=low, high=high)).mean
    aim = aim.numpy()
    clipped = np.clip(aim, TARGET_AREA.low, TARGET_AREA.high)
    return clipped, throw(clipped, rng=rng, noise=noise).hit, np.any(clipped != aim, axis=1)


def rms(error):
    """Per-axis RMS ``(2,)`` of ``(n, 2)`` errors."""
    return np.sqrt(np.mean(np.square(error), axis=0))


def select_bins(targets, hits, candidates, rng, noise, validation_share=0.2, progress=True):
    """Re-throw RMS on a validation split for each grid size; rows of a table."""
    n_val = max(1, int(round(validation_share * len(targets))))
    table = []
    for k in tqdm(candidates, desc="clusters per axis", disable=not progress):
        model = fit_throws((k, k), targets[n_val:], hits[n_val:])
        desired = hits[:n_val]
        error = rethrow(model, desired, rng, noise)[1] - desired
        y, z = rms(error)
        table.append({"bins": k, "rms_y_m": y, "rms_z_m": z, "rms_m": float(np.hypot(y, z))})
    return table


def evaluate(bins, train, test, rng, noise):
    """Fit on ``train``, re-throw every test hit; RMS per axis, timings and the errors."""
    start = time.perf_counter()
    model = fit_throws(bins, *train)
    fitted = time.perf_counter()
    aim, new_hit, clipped = rethrow(model, test[1], rng, noise)
    done = time.perf_counter()
    error = new_hit - test[1]
    return {
        "rms": rms(error),
        "error": error,
        "aim": aim,
        "clipped": int(clipped.sum()),
        "fit_s": fitted - start,
        "query_s": done - fitted,
    }


@dataclass
class ThrowingResult(Result):
    """What :func:`run_throwing` measured: RMS errors in metres per axis ``y``, ``z``.

    ``rms_*``: the chosen grid (``bins``, ``n_clusters``) without noise; ``*_single_gaussian``:
    one cluster; ``*_noisy``: the chosen grid trained and re-thrown with release noise
    (``*_noisy_reachable``: test hits a noise-free throw can reach), beside
    ``noise_scatter_*``. ``cluster_selection``: validation RMS per grid size;
    ``per_hit``: per panel of the figure, the test hits ``(n, 2)`` and their re-throw
    errors ``(n, 2)``, metres.
    """

    experiment_name: ClassVar[str] = "throwing"

    n_train: int
    n_test: int
    seed: int
    n_clusters: int
    bins: list[int]
    paper_rms_y_m: float
    paper_rms_z_m: float
    rms_y_m: float
    rms_z_m: float
    rms_y_m_single_gaussian: float
    rms_z_m_single_gaussian: float
    rms_y_m_noisy: float
    rms_z_m_noisy: float
    rms_y_m_noisy_reachable: float
    rms_z_m_noisy_reachable: float
    noise_scatter_y_m: float
    noise_scatter_z_m: float
    release_noise: dict[str, float]
    test_hits_unreachable: int
    test_hits_unreachable_noisy: int
    aims_clipped: dict[str, int]
    cluster_selection: list[dict]
    timings_s: dict[str, float]
    per_hit: dict[str, dict] = field(repr=False)

    def to_markdown(self) -> str:
        """The selection table and the paper's figures beside ours, in cm."""
        k = self.bins[0]
        lines = [
            f"# Throwing: re-thrown RMS over {self.n_test} test hits "
            f"({self.n_train} training throws)",
            "",
            "| | y (cm) | z (cm) |",
            "|---|---:|---:|",
        ]
        for label, key in (
            ("paper (its x, y)", "paper_rms_{}_m"),
            (f"ours, {k} x {k} clusters, noise-free", "rms_{}_m"),
            ("ours, single Gaussian, noise-free", "rms_{}_m_single_gaussian"),
            (f"ours, {k} x {k} clusters, release noise", "rms_{}_m_noisy"),
            ("the same, reachable test hits only", "rms_{}_m_noisy_reachable"),
            ("the noise's own scatter (no inverse beats it)", "noise_scatter_{}_m"),
        ):
            y, z = (100 * getattr(self, key.format(axis)) for axis in ("y", "z"))
            lines.append(f"| {label} | {y:.3f} | {z:.3f} |")
        lines += [
            "",
            f"Goal: under {100 * GOAL_RMS_M:g} cm on both axes, noise-free. Grid chosen by "
            "the validation re-throw RMS (cm):",
            "",
            "| clusters per axis | y | z |",
            "|---:|---:|---:|",
        ]
        for row in self.cluster_selection:
            lines.append(
                f"| {row['bins']} | {100 * row['rms_y_m']:.3f} | {100 * row['rms_z_m']:.3f} |"
            )
        lines += [
            "",
            f"Test hits no noise-free throw reaches: {self.test_hits_unreachable} noise-free, "
            f"{self.test_hits_unreachable_noisy} noisy (kept in the RMS: their aims are thrown "
            f"like the others); aims clipped into the area: {self.aims_clipped}.",
            "",
        ]
        return "\n".join(lines)

    def figures(self, out: Path) -> list[Path]:
        """Draw the re-throw errors, ``throwing_errors.png``, into the folder ``out``; its path."""
        return [plot_errors(self, out / "throwing_errors.png")]

    def summary_rows(self, results) -> list[str]:
        """The results table's row of the throw, beside the paper's."""
        return [
            f"| §IV-B throw: re-thrown RMS y / z (m) | {self.paper_rms_y_m:.4f} / "
            f"{self.paper_rms_z_m:.4f} | {self.rms_y_m:.4f} / {self.rms_z_m:.4f} "
            f"({self.n_clusters} clusters; one Gaussian: {self.rms_y_m_single_gaussian:.4f} / "
            f"{self.rms_z_m_single_gaussian:.4f}; with release noise {self.rms_y_m_noisy:.4f} / "
            f"{self.rms_z_m_noisy:.4f} beside the noise's own scatter "
            f"{self.noise_scatter_y_m:.4f} / {self.noise_scatter_z_m:.4f}) | |"
        ]


def run_throwing(config: ThrowingConfig) -> ThrowingResult:
    """Choose the grid, re-throw the test hits with and without release noise."""
    n = config.n_train + config.n_test
    seeds = np.random.SeedSequence(config.seed).spawn(3)
    exact = get_data(n, np.random.default_rng(seeds[0]), None)
    noise, noise_rng = ReleaseNoise(), np.random.default_rng(seeds[1])
    noisy = get_data(n, np.random.default_rng(seeds[2]), noise)
    split = [(t[: config.n_train], h[: config.n_train]) for t, h in (exact, noisy)]
    tests = [(t[config.n_train :], h[config.n_train :]) for t, h in (exact, noisy)]

    table = select_bins(*split[0], config.bins, None, None, progress=config.progress)
    k = min(table, key=lambda row: row["rms_m"])["bins"]
    runs = {
        "clusters": evaluate((k, k), split[0], tests[0], None, None),
        "single": evaluate((1, 1), split[0], tests[0], None, None),
        "noisy": evaluate((k, k), split[1], tests[1], noise_rng, noise),
    }
    # The noise's own scatter: the same aims thrown with and without noise.
    aims = runs["noisy"]["aim"]
    scatter = rms(throw(aims, rng=noise_rng, noise=noise).hit - throw(aims).hit)
    reachable = is_reachable_hit(tests[1][1])
    noisy_reachable = rms(runs["noisy"]["error"][reachable])
    panels = {
        f"{k} x {k} clusters, noise-free": (tests[0][1], runs["clusters"]),
        "single Gaussian, noise-free": (tests[0][1], runs["single"]),
        f"{k} x {k} clusters, release noise": (tests[1][1], runs["noisy"]),
    }
    return ThrowingResult(
        n_train=config.n_train,
        n_test=config.n_test,
        seed=config.seed,
        n_clusters=k * k,
        bins=[k, k],
        paper_rms_y_m=PAPER_RMS_M["y"],
        paper_rms_z_m=PAPER_RMS_M["z"],
        rms_y_m=float(runs["clusters"]["rms"][0]),
        rms_z_m=float(runs["clusters"]["rms"][1]),
        rms_y_m_single_gaussian=float(runs["single"]["rms"][0]),
        rms_z_m_single_gaussian=float(runs["single"]["rms"][1]),
        rms_y_m_noisy=float(runs["noisy"]["rms"][0]),
        rms_z_m_noisy=float(runs["noisy"]["rms"][1]),
        rms_y_m_noisy_reachable=float(noisy_reachable[0]),
        rms_z_m_noisy_reachable=float(noisy_reachable[1]),
        noise_scatter_y_m=float(scatter[0]),
        noise_scatter_z_m=float(scatter[1]),
        release_noise={
            "direction_std_deg": noise.direction_std_deg,
            "speed_rel_std": noise.speed_rel_std,
        },
        test_hits_unreachable=int((~is_reachable_hit(tests[0][1])).sum()),
        test_hits_unreachable_noisy=int((~reachable).sum()),
        aims_clipped={name: run["clipped"] for name, run in runs.items()},
        cluster_selection=[
            {key: float(v) if key != "bins" else int(v) for key, v in row.items()} for row in table
        ],
        timings_s={
            f"{name}_{t}": run[t] for name, run in runs.items() for t in ("fit_s", "query_s")
        },
        per_hit={
            title: {"hits": hits.tolist(), "error": run["error"].tolist()}
            for title, (hits, run) in panels.items()
        },
    )


def plot_errors(result: ThrowingResult, path) -> Path:
    """Error magnitude of each re-throw over the target plane, and the selection curve."""
    from matplotlib.colors import LogNorm
    from matplotlib.figure import Figure

    fig = Figure(figsize=(12, 10), layout="constrained")
    axes = fig.subplots(2, 2)
    boundary = reachable_hit_boundary(200)
    norm = LogNorm(1e-2, 20.0)
    for ax, (title, run) in zip(axes.flat, result.per_hit.items(), strict=False):
        hits, error = np.array(run["hits"]), np.array(run["error"])
        ax.fill(*boundary.T, color="tab:green", alpha=0.1, lw=0, label="reachable hits")
        ax.add_patch(_rectangle(TARGET_AREA, label="target area"))
        cm = 100 * np.linalg.norm(error, axis=1)
        title += "\nRMS y {:.2f} cm, z {:.2f} cm".format(*(100 * rms(error)))
        art = ax.scatter(
            *hits.T, c=np.clip(cm, norm.vmin, norm.vmax), s=9, cmap="viridis", norm=norm
        )
        ax.set(title=title, xlabel="y [m] (robot's left <-)", ylabel="z [m]", aspect="equal")
        ax.invert_xaxis()  # as the robot sees the wall
        ax.legend(loc="upper right", fontsize=7)
    fig.colorbar(art, ax=axes, shrink=0.6, label="|new hit - desired hit| [cm]")
    ax, table, chosen = axes[1, 1], result.cluster_selection, result.bins[0]
    ks = [row["bins"] for row in table]
    for key, label in (("rms_y_m", "y"), ("rms_z_m", "z")):
        ax.plot(ks, [100 * row[key] for row in table], "o-", label=f"validation RMS {label}")
    ax.axvline(chosen, color="grey", ls="--", label=f"chosen: {chosen} x {chosen}")
    ax.set(xlabel="clusters per axis", ylabel="RMS [cm]", yscale="log", title="Choosing the grid")
    ax.legend(fontsize=8)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    return path


def _rectangle(area, **kwargs):
    from matplotlib.patches import Rectangle

    return Rectangle(
        (area.y_min, area.z_min),
        area.y_max - area.y_min,
        area.z_max - area.z_min,
        fill=False,
        color="black",
        lw=1,
        **kwargs,
    )


EXPERIMENTS = (
    Experiment(
        ThrowingConfig,
        run_throwing,
        ThrowingResult,
        order=40,
        tiny={"n_train": 100, "n_test": 10, "bins": (1, 2)},
        quick=QUICK,
    ),
)

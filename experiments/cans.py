"""The can data set at a scale, and the can network (Fig. 2) fitted on one angle's throws.

Shared by the can experiments (:mod:`experiments.can_tossing`, :mod:`experiments.combined`,
:mod:`experiments.physics_bounds`, :mod:`experiments.active`); composes sim2d (data),
models (the network) and inference (fitting, compiled queries). Their common settings
are written once here: :class:`SimulationSettings` (where simulations are saved and
run) and :class:`CanDataSettings` (those and the data set's scale).

Generated data has one home (docs/data.md): the folder a command names (``--data-dir``),
else :func:`default_data_dir`, ``data`` in the cache folder of
:func:`sim2d.configurations.cache_dir` (``$EFFECT_NETWORKS_CACHE``, else
``~/.cache/effect-networks``), whatever the current directory.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from effect_networks.experiments.evaluation import aim_robust_best
from effect_networks.experiments.harness.config import check_choice, check_executor
from effect_networks.inference import CompiledQueries, fit, predict
from effect_networks.inference import compile as compile_queries
from effect_networks.models import EffectNetwork, NetworkParams
from effect_networks.models.can_pyramid import can_network, can_rows
from effect_networks.sim2d import field_throws, geometry
from effect_networks.sim2d.can_dataset import CanDataset, generate_dataset, load_dataset
from effect_networks.sim2d.configurations import cache_dir, stable_configurations

__all__ = [
    "SCALES",
    "CanDataSettings",
    "BOUND_SEED",
    "CanModel",
    "Replays",
    "SimulationSettings",
    "can_dataset",
    "choose",
    "default_data_dir",
    "fit_can_network",
    "fit_on_replays",
    "replays",
    "start_configurations",
]

#: Seed of the simulator's own repeated throws (:func:`replays`); the training data set uses
#: seed 0, so these throws are fresh.
BOUND_SEED = 1

#: Scales: how many start configurations (None: all) and repeats per throw.
SCALES = {
    "full": {"n_configs": None, "repeats": 3},
    "quick": {"n_configs": 16, "repeats": 3},
    "tiny": {"n_configs": 3, "repeats": 1},
}


def default_data_dir() -> Path:
    """Where generated data is saved unless a folder is named.

    ``data`` in the cache folder (``$EFFECT_NETWORKS_CACHE``, else ``~/.cache/effect-networks``).
    """
    return cache_dir() / "data"


@dataclass(frozen=True)
class SimulationSettings:
    """Settings of an experiment that simulates; checked on construction.

    Attributes
    ----------
    data_dir : Path
        Where the simulations are saved as they finish, and resumed or reused from
        (default: data in the cache folder, $EFFECT_NETWORKS_CACHE or
        ~/.cache/effect-networks).
    executor : str or None
        Where they run (:mod:`sim2d.executors`): process:N | dask-local:N |
        dask://HOST:PORT | ray; None: every core here.
    """

    data_dir: Path | None = None
    executor: str | None = None

    def __post_init__(self):
        folder = default_data_dir() if self.data_dir is None else Path(self.data_dir)
        object.__setattr__(self, "data_dir", folder)
        check_executor("executor", self.executor)


@dataclass(frozen=True)
class CanDataSettings(SimulationSettings):
    """Settings of an experiment on the can data set (:func:`can_dataset`).

    Attributes
    ----------
    scale : str
        The can data set's scale, a key of ``SCALES`` (full, quick, tiny).
    """

    scale: str = "full"

    def __post_init__(self):
        check_choice("scale", self.scale, SCALES)
        super().__post_init__()


def start_configurations(n_configs: int | None) -> list[int]:
    """All stable configurations, or a spread of ``n_configs`` of them with the full pyramid."""
    stable = list(stable_configurations())
    if n_configs is None or n_configs >= len(stable):
        return stable
    by_count = sorted(stable, key=lambda m: (-bin(m).count("1"), m))  # full pyramid first
    step = len(by_count) / n_configs
    return sorted({by_count[int(i * step)] for i in range(n_configs)})


def can_dataset(
    data_dir: Path,
    scale: str,
    *,
    angles=(0, 1, 2),
    seed: int = 0,
    progress: bool = True,
    executor=None,
) -> CanDataset:
    """Generate (or reuse, or resume) the can data set at ``scale`` and load it.

    Saved as ``data_dir/can_dataset.npz`` at full scale, ``can_dataset_<scale>.npz``
    otherwise; ``executor``: where it is simulated
    (:func:`sim2d.can_dataset.generate_dataset`).
    """
    if scale not in SCALES:
        raise ValueError(f"scale={scale!r} is not one of {', '.join(map(repr, SCALES))}")
    spec = SCALES[scale]
    configs = start_configurations(spec["n_configs"])
    name = "can_dataset.npz" if scale == "full" else f"can_dataset_{scale}.npz"
    path = generate_dataset(
        Path(data_dir) / name,
        configs=configs,
        angles=angles,
        repeats=spec["repeats"],
        seed=seed,
        executor=executor,
        progress=progress,
    )
    return load_dataset(path)


@dataclass(frozen=True)
class Replays:
    """The simulator's own repeated 0° throws: every field from every non-empty start.

    ``configs``: the start masks, sorted; ``end_config`` and ``count_after``: ``(configs, 195,
    repeats)`` int64, the outcome of each repeat (an unthrowable field's rows are its start, not
    simulated).
    """

    configs: tuple[int, ...]
    end_config: np.ndarray
    count_after: np.ndarray

    @property
    def repeats(self) -> int:
        """Throws per (start, field)."""
        return self.end_config.shape[-1]

    def head(self, repeats: int) -> Replays:
        """The first ``repeats`` throws of each (start, field)."""
        assert 1 <= repeats <= self.repeats
        return Replays(
            self.configs, self.end_config[..., :repeats], self.count_after[..., :repeats]
        )

    def row(self, start: int) -> int:
        """The index of the start configuration ``start`` in ``configs``."""
        return self.configs.index(int(start))


def replays(
    data_dir: Path, scale: str, repeats: int, *, angle: int = 0, executor=None, progress=True
) -> Replays:
    """Every field thrown ``repeats`` times at ``angle`` from every non-empty start at ``scale``.

    With the data set's jitter and fresh seeds (``BOUND_SEED``); generated once as
    ``data_dir/can_bound_<scale>_<repeats>.npz`` (resumed when interrupted) and shared by every
    experiment that asks for the same replays.
    """
    configs = [c for c in start_configurations(SCALES[scale]["n_configs"]) if c]
    path = generate_dataset(
        Path(data_dir) / f"can_bound_{scale}_{repeats}.npz",
        configs=configs,
        angles=(angle,),
        repeats=repeats,
        seed=BOUND_SEED,
        executor=executor,
        progress=progress,
    )
    sims = load_dataset(path)
    order = np.lexsort((sims.repeat, sims.field, sims.start_config))
    shape = (len(configs), geometry.N_FIELDS, repeats)
    return Replays(
        tuple(sorted(configs)),
        sims.end_config[order].astype(np.int64).reshape(shape),
        sims.count_after[order].astype(np.int64).reshape(shape),
    )


@dataclass(frozen=True)
class CanModel:
    """The can network fitted on one angle's data, with its compiled query tables."""

    angle: int
    net: EffectNetwork
    params: NetworkParams
    compiled: CompiledQueries
    throwable: torch.Tensor  # (195,) bool: fields the ball can reach at this angle

    def best_fields(self, start: np.ndarray, desired_count: np.ndarray) -> np.ndarray:
        """Best field per row for ``(start mask, desired end count)``, never an unthrowable one."""
        post = self.compiled.infer_action(
            {
                "initial.config": start,
                "initial.count": np.array([bin(int(m)).count("1") for m in start]),
                "end.count": np.asarray(desired_count, dtype=np.int64),
            },
            allowed=self.throwable,
        )
        return post.best.numpy()

    def end_config_probs(self, start: int, fields: np.ndarray | None = None) -> torch.Tensor:
        """``(n_fields, n_states)``: predicted end configuration for each field from ``start``."""
        fields = np.arange(len(self.net.actions)) if fields is None else np.asarray(fields)
        n = len(fields)
        ev = {
            "initial.config": np.full(n, start),
            "initial.count": np.full(n, bin(int(start)).count("1")),
            "action": [self.net.actions[f] for f in fields],
        }
        return predict(self.net, self.params, ev).discrete["config"]

    @property
    def states(self) -> tuple[int, ...]:
        """The end configurations the network has states for (masks), in state order."""
        return tuple(int(s) for s in self.net.feature("config").states)


def fit_can_network(data: CanDataset, angle: int) -> CanModel:
    """Fit Fig. 2's network by maximum likelihood on the throwable throws at ``angle``."""
    sel = (data.angle == angle) & data.throwable
    if not sel.any():
        raise ValueError(
            f"the data set has no throwable throws at angle {angle} ({geometry.ANGLE_NAMES[angle]})"
        )
    starts = set(data.start_config.tolist())
    return _fit_throws(starts, data.start_config[sel], data.field[sel], data.end_config[sel], angle)


def fit_on_replays(sims: Replays, angle: int = 0) -> CanModel:
    """Fit Fig. 2's network on replays (:func:`replays`) thrown at ``angle``, as on a data set.

    Every throwable field's replays from every start are training throws: a network that
    saw ``sims.repeats`` throws per aim where the data set has a few.
    """
    throwable = np.array([field_throws.is_throwable(f, angle) for f in range(geometry.N_FIELDS)])
    if not throwable.any():
        raise ValueError(f"no field is throwable at angle {angle}")
    shape = sims.end_config.shape
    start = np.broadcast_to(np.asarray(sims.configs, np.int64)[:, None, None], shape)
    field = np.broadcast_to(np.arange(geometry.N_FIELDS)[None, :, None], shape)
    sel = np.broadcast_to(throwable[None, :, None], shape)
    return _fit_throws(set(sims.configs), start[sel], field[sel], sims.end_config[sel], angle)


def _fit_throws(starts: set, start, field, end, angle: int) -> CanModel:
    """Fig. 2's network over the ``starts`` and every end seen, fitted on the throws given."""
    states = sorted(set(starts) | set(np.asarray(end).tolist()))
    net = can_network(states)
    params = fit(net, can_rows(net, start, field, end)).params
    throwable = torch.tensor(
        [field_throws.is_throwable(f, angle) for f in range(geometry.N_FIELDS)]
    )
    return CanModel(angle, net, params, compile_queries(net, params), throwable)


def choose(model: CanModel, evidence: dict, rule: str) -> np.ndarray:
    """Best field per row for ``evidence``: the query's argmax or the aim-robust one.

    Rows of equal evidence (many of Table I's cases share a start and a desired count) are answered
    once.
    """
    enc = model.net.encode(evidence)
    if enc.n_rows == 0:
        return _choose(model, enc, rule)
    keys = torch.stack([enc[s] for s in enc], 1)
    _, group = torch.unique(keys, dim=0, return_inverse=True)
    first = torch.full((int(group.max()) + 1,), len(group)).scatter_reduce(
        0, group, torch.arange(len(group)), "amin"
    )
    return _choose(model, enc.rows(first), rule)[group.numpy()]


def _choose(model: CanModel, evidence, rule: str) -> np.ndarray:
    post = model.compiled.infer_action(evidence, allowed=model.throwable)
    if rule == "index":
        return post.best.numpy()
    allowed = model.throwable.expand_as(post.probs) & (post.unseen < 0.5)
    allowed = torch.where(allowed.any(-1, keepdim=True), allowed, model.throwable)
    return aim_robust_best(
        post.probs, (geometry.N_ROWS, geometry.N_COLUMNS), allowed=allowed
    ).numpy()

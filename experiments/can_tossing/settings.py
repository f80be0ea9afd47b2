"""Can tossing's settings and constants: protocols, tie-breaks, the paper's Table I.

The experiment is described in :mod:`experiments.can_tossing`.
"""

from __future__ import annotations

from dataclasses import dataclass

from effect_networks.experiments.cans import CanDataSettings
from effect_networks.experiments.evaluation import ACCURACY_BINS
from effect_networks.experiments.harness.config import check_choice, check_float, check_int
from effect_networks.sim2d import geometry

__all__ = [
    "AIM_SIGMAS",
    "ANGLE",
    "CHUNK",
    "CONVERGE",
    "CanTossingConfig",
    "DEMO",
    "FAILURE_LABELS",
    "MAX_AIM_ERROR",
    "PAPER_CASES",
    "PAPER_PERCENT",
    "PAPER_TABLE_I",
    "PERTURB",
    "PICK",
    "PROTOCOLS",
    "REPLAY",
    "RULES",
    "TABLE_I",
    "TABLE_I_PROTOCOLS",
    "VALIDATE",
]

#: Table I's cases, see :func:`experiments.can_tossing.run.table_one_cases`
PROTOCOLS = ("counts", "actions")
#: tie-breaks among fields of equal posterior
RULES = ("index", "aim")
#: The largest imitation aim error, m per axis: half the pyramid's height. Beyond it most
#: perturbed throws miss the cans altogether and the ROC would measure only that.
MAX_AIM_ERROR = geometry.PYRAMID_HEIGHT / 2


@dataclass(frozen=True)
class CanTossingConfig(CanDataSettings):
    """Settings of :func:`experiments.can_tossing.run.run_can_tossing`; every field is checked on construction.

    The can data set's: :class:`experiments.cans.CanDataSettings`.

    Attributes
    ----------
    seed : int
        Seeds every evaluation throw (>= 0).
    rule, cases : str
        The headline's tie-break (``RULES``) and protocol (``PROTOCOLS``); all four are
        measured either way.
    n_demos : int
        Emulation demonstrations, and imitation throws (each of the test and the
        validation draw).
    aim_error : float
        Imitation's aim error, m per axis, in ``(0, MAX_AIM_ERROR]``.
    n_ordinary : int
        Imitation: ordinary (jittered) throws of the intended field that tell its usual
        outcomes.
    bound_repeats : int
        Imitation's physics bound: replays of every field from every start (>= 2), the
        physics bounds' Table I replays when the numbers agree
        (:func:`experiments.cans.replays`).
    curve_repeats : int
        Imitation's bound as the replays grow: fresh replays of each scored throw's own
        start and field (>= 2); the bound is measured from the first 2, 4, 8, ... of them
        and from all (:func:`experiments.can_tossing.surprise.bound_curve`).
    progress : bool
        Progress bars.
    """

    seed: int = 0
    rule: str = "aim"
    cases: str = "counts"
    n_demos: int = 300
    aim_error: float = 0.03
    n_ordinary: int = 8
    bound_repeats: int = 16
    curve_repeats: int = 256
    progress: bool = True

    def __post_init__(self):
        super().__post_init__()
        check_int("seed", self.seed, 0)
        check_choice("rule", self.rule, RULES)
        check_choice("cases", self.cases, PROTOCOLS)
        check_int("n_demos", self.n_demos, 1)
        check_float("aim_error", self.aim_error, 0.0, MAX_AIM_ERROR, low_open=True, unit="m")
        check_int("n_ordinary", self.n_ordinary, 1)
        check_int("bound_repeats", self.bound_repeats, 2)
        check_int("curve_repeats", self.curve_repeats, 2)


ANGLE = 0  # the paper trains and evaluates at 0°
PAPER_TABLE_I = dict(zip(ACCURACY_BINS, (36, 63, 309, 7780, 269, 113, 33), strict=True))
PAPER_PERCENT = dict(zip(ACCURACY_BINS, (0.41, 0.73, 3.59, 90.43, 3.12, 1.31, 0.38), strict=True))
PAPER_CASES = 8603
# Seed purposes: every evaluation throw draws its aim jitter from SeedSequence([seed,
# purpose]), never from the data set's per-throw seeds (SeedSequence of five numbers).
TABLE_I, DEMO, REPLAY, PERTURB, PICK, VALIDATE, CONVERGE = 1, 2, 3, 4, 5, 6, 7
CHUNK = 100  # throws per executor task
#: Aim errors (in fields) the pooled imitation surprise chooses among; 0: no pooling.
AIM_SIGMAS = (0.0, 0.25, 0.5, 0.75, 1.0, 1.5)

#: Imitation's failure labels (:func:`experiments.can_tossing.run.perturbed_throws`): not the
#: unperturbed throw's outcome; none of the intended throw's usual outcomes.
FAILURE_LABELS = ("failed", "failed_ordinary")

#: Table I's protocols (:data:`PROTOCOLS`) in the results table's words.
TABLE_I_PROTOCOLS = {
    "counts": "one case per reachable desired count",
    "actions": "one case per count-changing action, the paper's wording",
}

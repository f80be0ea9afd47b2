"""Materials and constants of the can world's simulation.

Bodies (the ball, the cans, the table), the friction and restitution of each pair of
materials, and the constants of the simulation itself: gravity, the fixed step, the
solver, pymunk's sleeping, the time cap and the thresholds of the outcome rules. The
step size, the solver iterations and the sleeping thresholds are part of the model:
outcomes change with them, so they are fixed here and recorded with every data set
(:func:`physical_constants`).

pymunk multiplies the two shapes' values of a pair, so each shape's friction and
elasticity (``*_SHAPE_*``) are derived from the pair values; pymunk's default collision
slop assumes pixels and is set to half a millimetre.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import pymunk
from effect_networks.sim2d import geometry

__all__ = [
    "BALL_ELASTICITY_SHAPE",
    "BALL_FRICTION_SHAPE",
    "BALL_MASS",
    "BALL_RADIUS",
    "CAN_ELASTICITY_SHAPE",
    "CAN_FRICTION_SHAPE",
    "CAN_MASS",
    "CHECK_EVERY",
    "COLLISION_SLOP",
    "ELASTICITY_BALL_CAN",
    "ELASTICITY_CAN_CAN",
    "ELASTICITY_CAN_TABLE",
    "FALLEN_DEPTH",
    "FRICTION_BALL_CAN",
    "FRICTION_CAN_CAN",
    "FRICTION_CAN_TABLE",
    "GRAVITY",
    "IDLE_SPEED",
    "MAX_SIM_TIME",
    "STEPPING",
    "STOPPING",
    "STOPPING_FORMAT_1",
    "SOLVER_ITERATIONS",
    "TABLE_CLEARANCE",
    "TABLE_ELASTICITY_SHAPE",
    "TABLE_FRICTION_SHAPE",
    "TABLE_MARGIN",
    "TABLE_THICKNESS",
    "THROWN_OFF_HORIZONTAL",
    "THROWN_OFF_VERTICAL",
    "TIME_STEP",
    "Stepping",
    "StoppingRules",
    "physical_constants",
]

# --- bodies ------------------------------------------------------------------------------
GRAVITY = 9.81  # m/s², acting along -z
BALL_MASS = 2.0  # kg
# m; a 2 kg ball 12 cm across (density ~2200 kg/m³, a small medicine ball). The radius
# must lie between the bottom field row's centre height (0.025 m) and the second row's
# (0.074 m) so that exactly the bottom row is too low to throw at flat.
BALL_RADIUS = 0.06
CAN_MASS = 0.1  # kg; an empty steel food tin of 12 cm x 16 cm weighs about 0.1 kg
TABLE_MARGIN = 1.5  # m, the table top reaches this far past both faces of the pyramid
TABLE_THICKNESS = 0.1  # m

# --- materials: Coulomb friction and restitution of each pair ----------------------------
# Engineering tables: dry steel on steel ~0.4-0.6, steel on wood ~0.2-0.6; a tin can
# bounces little.
FRICTION_CAN_CAN = 0.4
FRICTION_CAN_TABLE = 0.4
FRICTION_BALL_CAN = 0.4
ELASTICITY_CAN_CAN = 0.2
ELASTICITY_CAN_TABLE = 0.2
ELASTICITY_BALL_CAN = 0.4

# --- simulation (part of the model: outcomes depend on them) ------------------------------


@dataclass(frozen=True)
class Stepping:
    """How the can world is stepped.

    Attributes
    ----------
    time_step : float
        Seconds per step, fixed.
    solver_iterations : int
        pymunk's contact-solver iterations per step.
    start_asleep : bool
        The cans start asleep (pymunk's sleeping, as one group) at their standard
        positions: they stand exactly still and cost nothing to step until something
        touches one of them, which wakes them all. Otherwise they start awake and settle
        into their contacts during the first steps.
    """

    time_step: float
    solver_iterations: int
    start_asleep: bool


#: The stepping of the can world (data-set formats 1 and 2): 1 ms, pymunk's default 10 solver
#: iterations, the cans awake from the start. Faster steppings were measured and rejected
#: (benchmarks/sim.py): every one changed Table I by more than the tolerance.
STEPPING = Stepping(time_step=0.001, solver_iterations=10, start_asleep=False)
TIME_STEP = STEPPING.time_step  # s
SOLVER_ITERATIONS = STEPPING.solver_iterations
COLLISION_SLOP = 0.0005  # m; pymunk's default 0.1 assumes pixels
IDLE_SPEED = 0.01  # m/s below which a body counts as idle
MAX_SIM_TIME = 5.0  # s, the cap on every simulation
CHECK_EVERY = 10  # steps between checks of the stopping rules
FALLEN_DEPTH = 0.2  # m; a body this far below the table top has left the scene


@dataclass(frozen=True)
class StoppingRules:
    """When a simulated throw is over.

    Attributes
    ----------
    sleep_time : float
        Seconds a body must stay idle (below ``IDLE_SPEED``) before pymunk puts it to
        sleep; a run ends when every can sleeps.
    scene_margin : float
        Metres beyond the pyramid's faces: a body there moving away has left the scene
        for good and is removed (a can so removed counts as thrown off). Any margin
        above 4 cm removes only cans that moved more than 10 cm, i.e. thrown-off ones.
    """

    sleep_time: float
    scene_margin: float


#: The rules of the can world (data-set format 2): a body 10 cm past the pyramid's faces and
#: moving away has left the scene.
STOPPING = StoppingRules(sleep_time=0.2, scene_margin=0.1)
#: The rules of data-set format 1, which followed cans and ball 50 cm past the pyramid; the
#: end configuration differs from format 2's in a small fraction of throws (those where a
#: can or the ball 10-50 cm out still met another body). Kept to compare the two.
STOPPING_FORMAT_1 = StoppingRules(sleep_time=0.2, scene_margin=0.5)

# --- outcome rules -------------------------------------------------------------------------
TABLE_CLEARANCE = 0.01  # m; a throwable parabola keeps the ball this far above the table
# A can at rest is thrown off when it moved more than this.
THROWN_OFF_VERTICAL = 0.01  # m
THROWN_OFF_HORIZONTAL = 0.10  # m


# Shape values whose pairwise products are the pair values above.
CAN_FRICTION_SHAPE = math.sqrt(FRICTION_CAN_CAN)
TABLE_FRICTION_SHAPE = FRICTION_CAN_TABLE / CAN_FRICTION_SHAPE
BALL_FRICTION_SHAPE = FRICTION_BALL_CAN / CAN_FRICTION_SHAPE
CAN_ELASTICITY_SHAPE = math.sqrt(ELASTICITY_CAN_CAN)
TABLE_ELASTICITY_SHAPE = ELASTICITY_CAN_TABLE / CAN_ELASTICITY_SHAPE
BALL_ELASTICITY_SHAPE = ELASTICITY_BALL_CAN / CAN_ELASTICITY_SHAPE


def physical_constants(
    stopping: StoppingRules = STOPPING, stepping: Stepping = STEPPING
) -> dict[str, float | int | str | list]:
    """Every constant that changes what the simulation does, for metadata and cache keys.

    Parameters
    ----------
    stopping : StoppingRules
        The stopping rules the throws run under.
    stepping : Stepping
        How the world is stepped.

    Returns
    -------
    dict
        Plain JSON-serialisable values, including the pymunk version.
    """
    g = geometry
    constants = {
        "n_cans": g.N_CANS,
        "row_sizes": list(g.ROW_SIZES),
        "can_width": g.CAN_WIDTH,
        "can_height": g.CAN_HEIGHT,
        "gap": g.GAP,
        "pyramid_x": g.PYRAMID_X,
        "n_columns": g.N_COLUMNS,
        "n_rows": g.N_ROWS,
        "angles": [list(a) for a in g.ANGLES],
        "angle_names": list(g.ANGLE_NAMES),
        "gravity": GRAVITY,
        "ball_mass": BALL_MASS,
        "ball_radius": BALL_RADIUS,
        "can_mass": CAN_MASS,
        "friction_can_can": FRICTION_CAN_CAN,
        "friction_can_table": FRICTION_CAN_TABLE,
        "friction_ball_can": FRICTION_BALL_CAN,
        "friction_ball_table": BALL_FRICTION_SHAPE * TABLE_FRICTION_SHAPE,
        "elasticity_can_can": ELASTICITY_CAN_CAN,
        "elasticity_can_table": ELASTICITY_CAN_TABLE,
        "elasticity_ball_can": ELASTICITY_BALL_CAN,
        "elasticity_ball_table": BALL_ELASTICITY_SHAPE * TABLE_ELASTICITY_SHAPE,
        "table_margin": TABLE_MARGIN,
        "time_step": stepping.time_step,
        "solver_iterations": stepping.solver_iterations,
        "collision_slop": COLLISION_SLOP,
        "sleep_time": stopping.sleep_time,
        "idle_speed": IDLE_SPEED,
        "max_sim_time": MAX_SIM_TIME,
        "check_every": CHECK_EVERY,
        "entry_x": g.ENTRY_X,
        "table_clearance": TABLE_CLEARANCE,
        "thrown_off_vertical": THROWN_OFF_VERTICAL,
        "thrown_off_horizontal": THROWN_OFF_HORIZONTAL,
        "scene_margin": stopping.scene_margin,
        "fallen_depth": FALLEN_DEPTH,
        "pymunk_version": pymunk.version,
    }
    if stepping.start_asleep:  # recorded only when set: older metadata and cache keys stay valid
        constants["start_asleep"] = True
    return constants

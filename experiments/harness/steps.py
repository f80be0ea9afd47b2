"""What one step of the main job measured about itself: its simulation time and its peak memory.

``./reproduce`` runs each step as a child process and names a file in the environment
variable ``STEP_RECORD_ENV``; the step's script (:func:`experiments.harness.config.run_script`)
writes its :class:`StepMeasure` there as it exits: the wall time it spent simulating
(:func:`sim2d.clock.simulation_seconds`) and the peak resident memory of its own process
(:func:`own_peak_bytes`) and of the largest process it started and waited for
(``getrusage``'s ``ru_maxrss`` of its children: its workers).
"""

from __future__ import annotations

import json
import os
import resource
import sys
from dataclasses import asdict, dataclass
from pathlib import Path

from effect_networks.sim2d.clock import simulation_seconds

__all__ = [
    "STEP_RECORD_ENV",
    "StepMeasure",
    "max_rss_bytes",
    "read_step_record",
    "write_step_record",
]

#: The environment variable naming the file a step writes its measures to.
STEP_RECORD_ENV = "EFFECT_NETWORKS_STEP_RECORD"


@dataclass(frozen=True)
class StepMeasure:
    """What one step measured about itself.

    ``simulation_seconds``: wall time spent simulating; ``peak_bytes``: peak resident memory of the
    step's process; ``children_peak_bytes``: that of the largest process it started and waited for
    (0: none).
    """

    simulation_seconds: float
    peak_bytes: int
    children_peak_bytes: int

    @property
    def largest_bytes(self) -> int:
        """The peak of the largest process of the step."""
        return max(self.peak_bytes, self.children_peak_bytes)


def max_rss_bytes(who: int) -> int:
    """``getrusage(who).ru_maxrss`` in bytes (kilobytes on Linux, bytes on macOS)."""
    peak = resource.getrusage(who).ru_maxrss
    return int(peak if sys.platform == "darwin" else peak * 1024)


def own_peak_bytes() -> int:
    """The peak resident memory of the running process.

    ``VmHWM`` of ``/proc/self/status`` where there is one (Linux), else ``ru_maxrss``. (On Linux
    ``ru_maxrss`` also keeps the peak of the process that started this one, up to the moment it
    started the program: a step started by a large process would seem as large.)
    """
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) * 1024
    except OSError:
        pass
    return max_rss_bytes(resource.RUSAGE_SELF)


def measure() -> StepMeasure:
    """The running process's measures so far."""
    return StepMeasure(
        simulation_seconds(), own_peak_bytes(), max_rss_bytes(resource.RUSAGE_CHILDREN)
    )


def write_step_record() -> Path | None:
    """Write :func:`measure` to the file ``$STEP_RECORD_ENV`` names; None where unset."""
    target = os.environ.get(STEP_RECORD_ENV)
    if not target:
        return None
    path = Path(target)
    path.write_text(json.dumps(asdict(measure())))
    return path


def read_step_record(path) -> StepMeasure | None:
    """The measures a step wrote to ``path``; None where it wrote none (it failed early)."""
    try:
        data = json.loads(Path(path).read_text())
        return StepMeasure(
            float(data["simulation_seconds"]),
            int(data["peak_bytes"]),
            int(data["children_peak_bytes"]),
        )
    except (OSError, ValueError, KeyError, TypeError):
        return None

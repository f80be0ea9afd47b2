"""The numbers every part of the toolkit computes with.

Every continuous value and every probability is float64 (:data:`DTYPE`). A continuous
value beyond ``+-MAX_MAGNITUDE`` is refused wherever evidence enters
(:func:`models.evidence.check_magnitude`).
"""

from __future__ import annotations

import torch

#: every continuous value and every probability is float64
DTYPE = torch.float64

#: Largest magnitude of a continuous value, for training and queries alike: its square,
#: summed over 10^7 rows, stays finite in float64.
MAX_MAGNITUDE = 1e150

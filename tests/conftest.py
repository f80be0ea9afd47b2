"""Test-session settings (one torch thread, the hypothesis profile) and the tiny can data set.

The suite's tensors are small; on a shared 2-core machine torch's thread pool spends
more time synchronising than computing (a gradient fit ran ten times slower with two
threads under load), and one thread makes every float sum run in one order.
"""

import os

import pytest
import torch
from hypothesis import settings

torch.set_num_threads(1)

# CI draws the same examples on every run (`HYPOTHESIS_PROFILE=ci`, set by .ci/run), so
# that a submission lands or fails on its own code; a local run explores new ones.
settings.register_profile("ci", derandomize=True, print_blob=True)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "default"))


@pytest.fixture(scope="session")
def tiny_data_dir(tmp_path_factory):
    """A data folder holding the tiny can data set (3 configurations, one repeat), made once
    for the session and shared by the experiments' and the examples' tests."""
    from effect_networks.experiments.cans import can_dataset

    folder = tmp_path_factory.mktemp("data")
    can_dataset(folder, "tiny", progress=False)
    return folder

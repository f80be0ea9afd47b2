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

# Every run draws the same examples, so that a change passes or fails on its own code;
# `HYPOTHESIS_PROFILE=explore ./run-tests` draws new ones.
settings.register_profile("fixed", derandomize=True, print_blob=True)
settings.register_profile("explore", print_blob=True)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE") or "fixed")


@pytest.fixture(scope="session")
def tiny_data_dir(tmp_path_factory):
    """A data folder holding the tiny can data set (3 configurations, one repeat), made once
    for the session and shared by the experiments' and the examples' tests."""
    from effect_networks.experiments.cans import can_dataset

    folder = tmp_path_factory.mktemp("data")
    can_dataset(folder, "tiny", progress=False)
    return folder

"""Fixtures shared by the sim2d tests: one small Dask cluster for the whole session."""

import pytest


@pytest.fixture(scope="session")
def dask_executor():
    """An executor on a Dask LocalCluster of 2 single-threaded worker processes."""
    pytest.importorskip("distributed")
    from effect_networks.sim2d.executors import open_executor

    with open_executor("dask-local:2") as executor:
        yield executor

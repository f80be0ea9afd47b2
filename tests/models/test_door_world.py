"""The door world (tests/inference/test_door_world.py) saved, loaded, declared and modelled:
files that fail or are damaged never pass for the model, and declarations that would
mean something else are refused by name."""

from __future__ import annotations

import errno
import os
import time

import numpy as np
import pytest
import torch
from effect_networks.models import Continuous, Discrete, EffectNetwork, Parameter, load, save

from tests.networks import DOOR_ACTIONS, DOOR_PARENTS, DOOR_STATES, door_rows, door_world


@pytest.fixture(scope="module")
def door():
    from effect_networks.inference import fit

    net = door_world()
    return net, fit(net, door_rows(600, seed=21)).params


def same(a, b) -> bool:
    return a.cpds.keys() == b.cpds.keys() and all(
        torch.equal(getattr(a[s], f), getattr(b[s], f))
        for s in a.cpds
        for f in a[s].__dataclass_fields__
    )


def test_a_failing_save_leaves_the_previous_file(door, tmp_path, monkeypatch):
    from effect_networks.inference import fit

    net, params = door
    path = save(tmp_path / "door.pt", net, params)
    other = fit(net, door_rows(300, seed=22)).params

    def full(fd):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(os, "fsync", full)  # the new file is written, never completed
    with pytest.raises(OSError, match="No space left"):
        save(path, net, other)
    monkeypatch.undo()
    loaded_net, loaded = load(path)
    assert loaded_net == net and same(loaded, params)
    assert [p.name for p in tmp_path.iterdir()] == ["door.pt"]  # no temporary file left
    save(path, net, other)
    assert same(load(path)[1], other)


def test_a_flipped_byte_is_refused(door, tmp_path):
    net, params = door
    data = (save(tmp_path / "door.pt", net, params)).read_bytes()
    rng = np.random.default_rng(0)
    damaged = tmp_path / "damaged.pt"
    refused = 0
    for i in rng.choice(len(data), 250, replace=False):
        flipped = bytearray(data)
        flipped[i] ^= 1 << int(rng.integers(8))
        damaged.write_bytes(bytes(flipped))
        try:
            loaded_net, loaded = load(damaged)
        except ValueError:
            refused += 1
            continue
        # a byte the format never reads (zip bookkeeping): the same model, bit for bit
        assert loaded_net == net and same(loaded, params), f"byte {i} changed the model"
    assert refused > 125


def reordered() -> EffectNetwork:
    features = (
        Discrete("door", ("shut", "locked", "open")),
        Discrete("drawer", DOOR_STATES["drawer"]),
        Discrete("switch", DOOR_STATES["switch"]),
        Continuous("handle_angle", 1),
    )
    return EffectNetwork(features=features, actions=DOOR_ACTIONS, parents=DOOR_PARENTS)


def test_loaded_parameters_refuse_a_declaration_with_states_reordered(door, tmp_path):
    from effect_networks.inference import infer_action, predict

    net, params = door
    _, loaded = load(save(tmp_path / "door.pt", net, params))
    other = reordered()
    evidence = {"initial.door": ["locked"], "initial.handle_angle": [[0.5]]}
    for call in (
        lambda: save(tmp_path / "other.pt", other, loaded),
        lambda: predict(other, loaded, evidence | {"action": ["turn"]}),
        lambda: infer_action(other, loaded, evidence | {"end.door": ["open"]}),
    ):
        with pytest.raises(ValueError, match=r"'initial\.door'.*states"):
            call()
    assert [p.name for p in tmp_path.iterdir()] == ["door.pt"]


def test_a_file_whose_declaration_was_edited_is_refused(door, tmp_path):
    # the states reordered inside the file (same length: the archive stays readable)
    net, params = door
    path = save(tmp_path / "door.pt", net, params)
    data = path.read_bytes()
    before, after = b'["locked", "shut", "open"]', b'["shut", "locked", "open"]'
    assert before in data
    path.write_bytes(data.replace(before, after))
    with pytest.raises(ValueError, match="checksum"):
        load(path)


def test_actions_given_as_one_string_are_refused():
    with pytest.raises(ValueError, match="'press'"):
        EffectNetwork(features=(Discrete("door", DOOR_STATES["door"]),), actions="press")


def test_a_billion_bins_are_refused_at_once_naming_the_site():
    start = time.perf_counter()
    with pytest.raises(ValueError, match=r"cluster\.force"):
        EffectNetwork(
            features=(Discrete("door", DOOR_STATES["door"]), Continuous("handle_angle", 1)),
            actions=DOOR_ACTIONS,
            parameters=(
                Parameter(
                    "force",
                    low=0.0,
                    high=1.0,
                    bins=10**9,
                    actions=("turn",),
                    affects="handle_angle",
                ),
            ),
        )
    assert time.perf_counter() - start < 1.0


def test_saving_onto_a_folder_is_refused_naming_it(door, tmp_path):
    net, params = door
    (tmp_path / "door.pt").mkdir()
    with pytest.raises(ValueError, match=r"'[^']*door\.pt' is a folder"):
        save(tmp_path / "door.pt", net, params)
    assert [p.name for p in tmp_path.iterdir()] == ["door.pt"]  # nothing written beside it


def test_states_or_actions_given_as_a_set_are_refused():
    # a set's order (each label's index) may differ from one run to the next
    with pytest.raises(ValueError, match=r"feature 'door': states must be an ordered sequence"):
        Discrete("door", set(DOOR_STATES["door"]))
    with pytest.raises(ValueError, match=r"actions must be an ordered sequence"):
        EffectNetwork(
            features=(Discrete("door", DOOR_STATES["door"]),), actions=frozenset(DOOR_ACTIONS)
        )


@pytest.mark.parametrize(
    ("end_sites", "words"),
    [
        ("end.door", r"end_sites must be a collection of end site names, got 'end\.door'"),
        ({"end.doors"}, r"end_sites \['end\.doors'\] are not sites of this network"),
    ],
)
def test_end_sites_that_would_leave_the_model_silently_are_refused(door, end_sites, words):
    # a string's letters, or a misspelt name, used to drop every end site without a word
    from effect_networks.models import effect_model
    from pyro.infer import TraceEnum_ELBO

    net, params = door
    evidence = net.encode({"initial.handle_angle": [[0.2]], "end.door": ["open"]})
    with pytest.raises(ValueError, match=words):
        TraceEnum_ELBO(max_plate_nesting=1).loss(
            lambda: effect_model(net, params, evidence, end_sites=end_sites), lambda: None
        )

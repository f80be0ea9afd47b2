"""Every fitted network saves and loads, bit for bit: drawn networks of every kind the
toolkit declares (tables, softmax, linear Gaussians of one or more dimensions, with or
without discrete parents, with a parameter on a grid or adaptive clusters), fitted every
way (closed form, chunked statistics, EM with gaps, EM over adaptive clusters), and a
learned structure."""

import math
from dataclasses import fields, replace

import numpy as np
import pytest
import torch
from effect_networks.inference import fit, fit_em, learn_structure, simulate
from effect_networks.models import (
    Continuous,
    Discrete,
    EffectNetwork,
    NetworkParams,
    load,
    random_params,
    save,
)
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from tests.networks import networks_of_every_kind, same_bits


def replace_site(params, site, cpd):
    return NetworkParams({**params.cpds, site: cpd}, params.pseudo_count)


def assert_same_numbers(net, params, path):
    back_net, back = load(save(path, net, params))
    assert back_net == net
    assert back.pseudo_count == params.pseudo_count
    assert set(back.cpds) == set(params.cpds)
    for site, cpd in params.cpds.items():
        for name in (f.name for f in fields(cpd)):
            value, other = getattr(cpd, name), getattr(back.cpds[site], name)
            if isinstance(value, torch.Tensor):
                assert same_bits(value.detach(), other), (site, name)
            else:
                assert value == other, (site, name)


ROUNDTRIP = settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])


@ROUNDTRIP
@given(net=networks_of_every_kind(), seed=st.integers(0, 2**16))
def test_random_params_of_any_network_roundtrip(tmp_path_factory, net, seed):
    params = random_params(net, seed)
    assert_same_numbers(net, params, tmp_path_factory.mktemp("save") / "net.pt")


def has_softmax(net) -> bool:
    return any(net.cpd(site.name).name == "softmax" for site in net.sites)


def rows_of(net, seed, n=120):
    return simulate(net, random_params(net, seed), n, seed=seed)


@ROUNDTRIP
@pytest.mark.filterwarnings("ignore::effect_networks.inference.ConvergenceWarning")
@pytest.mark.filterwarnings("ignore::effect_networks.inference.OutsideTrainingData")
@given(net=networks_of_every_kind(), seed=st.integers(0, 2**16), gaps=st.booleans())
def test_any_fitted_network_roundtrips(tmp_path_factory, net, seed, gaps):
    """Closed form (or EM over adaptive clusters), and EM over gaps in the end values."""
    rows = rows_of(net, seed)
    if gaps:
        for f in net.features:
            if isinstance(f, Continuous):
                values = torch.as_tensor(rows[f"end.{f.name}"]).clone()
                values[::7] = math.nan
                rows[f"end.{f.name}"] = values
    adaptive = any(p.layout == "adaptive" for p in net.parameters)
    if adaptive:
        # EM over adaptive clusters takes complete rows and closed-form CPDs
        assume(not gaps and not has_softmax(net))
        params = fit_em(net, rows, steps=3).params
    else:
        params = fit(net, rows, steps=3).params
    assert_same_numbers(net, params, tmp_path_factory.mktemp("save") / "net.pt")


@ROUNDTRIP
@given(net=networks_of_every_kind(), seed=st.integers(0, 2**16))
def test_chunked_fits_roundtrip(tmp_path_factory, net, seed):
    # chunks serve closed-form networks
    assume(not any(p.layout == "adaptive" for p in net.parameters) and not has_softmax(net))
    rows = rows_of(net, seed)
    halves = [{k: v[:60] for k, v in rows.items()}, {k: v[60:] for k, v in rows.items()}]
    params = fit(net, iter(halves)).params
    assert_same_numbers(net, params, tmp_path_factory.mktemp("save") / "net.pt")


def test_a_learned_structure_roundtrips(tmp_path):
    rng = np.random.default_rng(0)
    n = 400
    x = rng.normal(size=(n, 1))
    on = rng.random(n) < 0.5
    action = rng.choice(["push", "wait"], n)
    data = {
        "initial.x": x,
        "initial.on": on,
        "action": action,
        "end.x": x + (action == "push")[:, None] * 0.5 + rng.normal(0, 0.05, (n, 1)),
        "end.on": on ^ (action == "push"),
    }
    features = (Continuous("x", 1), Discrete("on", (False, True)))
    net = learn_structure(data, features, ("push", "wait"))
    assert_same_numbers(net, fit(net, data).params, tmp_path / "net.pt")


def test_a_one_dimensional_linear_gaussian_without_discrete_parents_saves(tmp_path):
    """The case that crashed: a 1-D continuous end feature whose only parent is its own
    initial value (its fitted bias was a view whose one dimension had stride 2)."""
    rng = np.random.default_rng(0)
    n = 200
    x = rng.normal(size=(n, 1))
    net = EffectNetwork((Continuous("x", 1),), ("a", "b"), parents={"end.x": ("initial.x",)})
    data = {
        "initial.x": x,
        "action": rng.choice(net.actions, n),
        "end.x": 2 * x + rng.normal(0, 0.1, (n, 1)),
    }
    assert_same_numbers(net, fit(net, data).params, tmp_path / "net.pt")


@pytest.mark.parametrize("dim", [1, 2])
def test_tensors_with_any_strides_save(tmp_path, dim):
    """Views with a size-1 dimension of any stride, transposed and sliced tensors: each
    saved as its numbers in order."""
    net = EffectNetwork((Continuous("x", dim),), ("a", "b"), parents={"end.x": ("initial.x",)})
    params = random_params(net, 0)
    site = "end.x"
    cpd = params.cpds[site]
    strided = {}
    for name in (f.name for f in fields(cpd)):
        value = getattr(cpd, name)
        if isinstance(value, torch.Tensor) and value.numel():
            wide = torch.stack([value, torch.full_like(value, 7.0)], dim=-1)
            strided[name] = wide[..., 0]  # every stride doubled
            assert strided[name].dim() == 0 or strided[name].stride(-1) == 2
    params = replace_site(params, site, replace(cpd, **strided))
    assert_same_numbers(net, params, tmp_path / "net.pt")

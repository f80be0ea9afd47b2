"""The effect model as a full Pyro model: Pyro's own handlers see what fit and queries see."""

import math

import numpy as np
import pyro
import pytest
import torch
from effect_networks.inference import infer_action, predict
from effect_networks.inference.exact.enumeration import enumerate_model
from effect_networks.models import (
    Continuous,
    Discrete,
    EffectNetwork,
    Parameter,
    effect_model,
    random_params,
)
from effect_networks.models.declaration import DTYPE
from pyro import poutine
from pyro.infer import Predictive, TraceEnum_ELBO, infer_discrete

from tests.helpers import spilling_network

NET = EffectNetwork(
    (Discrete("visible", (False, True)), Continuous("pos", 1)),
    ("look", "remove", "tap"),
    (Parameter("force", 0.0, 20.0, 4, ("tap",), "pos"),),
)
PARAMS = random_params(NET, 3)
START = {"initial.visible": [True], "initial.pos": [[0.1]]}


def site_names(data, **kwargs):
    trace = poutine.trace(effect_model).get_trace(NET, PARAMS, data, **kwargs)
    return [n for n, s in trace.nodes.items() if s["type"] == "sample"]


def test_sites_do_not_depend_on_the_data():
    full = site_names(None, n_rows=2)
    assert {"param.force", "cluster.force", "end.pos", "action"} <= set(full)
    assert site_names(START | {"action": ["tap"]}) == full
    assert site_names(START | {"action": ["tap"], "param.force": [[3.0]]}) == full
    assert site_names(START, collapse=True) == full


def test_conditioning_on_the_parameter_is_obeyed():
    # pyro.condition on param.force means what the force in the data means: the joint
    # (TraceEnum_ELBO's loss, all discrete sites summed out) is the same, and the cluster
    # is the force's cell.
    ev = NET.encode(START | {"action": ["tap"], "end.pos": [[1.3]]})
    force = torch.tensor([[10.0]], dtype=torch.float32)  # float32, as torch makes it
    elbo = TraceEnum_ELBO(max_plate_nesting=1)
    by_data = elbo.loss(
        lambda: effect_model(NET, PARAMS, ev | {"param.force": [[10.0]]}, collapse=True),
        lambda: None,
    )
    conditioned = poutine.condition(effect_model, data={"param.force": force})
    by_handler = elbo.loss(lambda: conditioned(NET, PARAMS, ev, collapse=True), lambda: None)
    marginal = elbo.loss(lambda: effect_model(NET, PARAMS, ev, collapse=True), lambda: None)
    assert abs(by_handler - by_data) < 1e-9
    assert abs(by_handler - marginal) > 0.1  # not the parameter integrated out
    with torch.random.fork_rng():
        torch.manual_seed(0)
        draw = infer_discrete(
            lambda: conditioned(NET, PARAMS, ev.repeat(50)), first_available_dim=-2, temperature=1
        )()
    assert draw["cluster.force"].tolist() == [2] * 50  # 10 N lies in cell 2 of 0..20 N


def test_predictive_samples_every_site():
    with torch.random.fork_rng():
        torch.manual_seed(1)
        draws = Predictive(effect_model, num_samples=7)(NET, PARAMS, n_rows=3)
    for site in NET.sites:
        assert site.name in draws
        assert draws[site.name].shape[:2] == (7, 3)
    assert draws["param.force"].shape == (7, 3, 1)


def test_vectorised_predictive_draws_from_the_tables():
    # parallel=True runs the model once over a plate of draws: the model broadcasts over
    # it, so its draws follow the same tables (the action's, the cluster's given tap)
    sites = [site.name for site in NET.sites]
    with torch.random.fork_rng():
        torch.manual_seed(3)
        draws = Predictive(effect_model, num_samples=4000, parallel=True, return_sites=sites)(
            NET, PARAMS, n_rows=2
        )
    assert set(draws) == set(sites)  # no factor sites (cluster.force.cell)
    action, cluster = draws["action"].flatten(), draws["cluster.force"].flatten()
    n = len(action)
    freq = torch.bincount(action, minlength=3).to(DTYPE) / n
    probs = PARAMS["action"].probs
    assert ((freq - probs).abs() <= 4 * (probs * (1 - probs) / n).sqrt() + 1e-12).all()
    tapped = cluster[action == 2]
    freq = torch.bincount(tapped, minlength=4).to(DTYPE) / len(tapped)
    probs = PARAMS["cluster.force"].probs[2]
    assert ((freq - probs).abs() <= 4 * (probs * (1 - probs) / len(tapped)).sqrt() + 1e-12).all()


def test_infer_discrete_samples_the_exact_action_posterior():
    ev = NET.encode(
        {
            "initial.visible": [True] * 400,
            "initial.pos": [[0.1]] * 400,
            "end.visible": [False] * 400,
        }
    )
    exact = infer_action(NET, PARAMS, ev).probs[0]

    def model():  # the unobserved continuous end.pos has no children: leave it out
        return effect_model(NET, PARAMS, ev, collapse=True, end_sites={"end.visible"})

    with torch.random.fork_rng():
        torch.manual_seed(2)
        action = infer_discrete(model, first_available_dim=-2, temperature=1)()["action"]
    freq = torch.bincount(action, minlength=3).to(DTYPE) / 400
    assert (freq - exact).abs().max() < 4 * math.sqrt(0.25 / 400)


def test_trace_enum_elbo_is_the_exact_log_evidence():
    ev = NET.encode(START | {"end.pos": [[0.8]], "end.visible": [False]})
    loss = TraceEnum_ELBO(max_plate_nesting=1).loss(
        lambda: effect_model(NET, PARAMS, ev, collapse=True), lambda: None
    )
    assert abs(loss + float(infer_action(NET, PARAMS, ev).log_evidence[0])) < 1e-9


@pytest.mark.filterwarnings("ignore:Found vars in model but not guide")  # end.pos, drawn
def test_trace_enum_elbo_is_exact_with_a_continuous_end_site_left_out():
    # end.pos unobserved: the collapsed model integrates it out (it has no children), so
    # the loss is -log p(evidence) on every call, not a draw of end.pos scored
    pushed = poutine.condition(effect_model, data={"param.force": torch.tensor([[10.0]])})
    tap = NET.encode(START | {"action": ["tap"], "end.visible": [False]})
    elbo = TraceEnum_ELBO(max_plate_nesting=1)
    losses = []
    for seed in range(5):
        with torch.random.fork_rng():
            torch.manual_seed(seed)
            losses.append(elbo.loss(lambda: pushed(NET, PARAMS, tap, collapse=True), lambda: None))
    # the documented idiom: only the observed end sites kept
    kept = elbo.loss(
        lambda: pushed(NET, PARAMS, tap, collapse=True, end_sites={"end.visible"}), lambda: None
    )
    # brute force: the initial state's, the action's, the cell's and the force's terms
    # and p(end.visible | visible, tap); end.pos integrates to one
    table = PARAMS["end.visible"]
    soft = table.weight[1, 2, :, 0] * 0.1 + table.bias[1, 2]
    prior = PARAMS["param.force"]
    start = PARAMS["initial.pos"]
    # a handler conditions the model itself: the cluster stays latent, summed out
    force = torch.distributions.Normal(prior.bias[:, 0], prior.scale_tril[:, 0, 0])
    want = (
        PARAMS["initial.visible"].probs[1].log()
        + PARAMS["action"].probs[2].log()
        + (
            PARAMS["cluster.force"].probs[2].log() + force.log_prob(torch.tensor(10.0, dtype=DTYPE))
        ).logsumexp(0)
        + soft.log_softmax(-1)[0]
        + torch.distributions.Normal(start.bias[0], start.scale_tril[0, 0]).log_prob(
            torch.tensor(0.1, dtype=DTYPE)
        )
    )
    assert max(abs(loss + float(want)) for loss in [*losses, kept]) < 1e-9


def test_float32_inputs_work():
    ev = NET.encode(START | {"action": ["tap"]})
    cond = poutine.condition(
        effect_model,
        data={"param.force": torch.tensor([[10.0]]), "end.pos": torch.tensor([[1.0]])},
    )
    trace = poutine.trace(cond).get_trace(NET, PARAMS, ev)
    trace.compute_log_prob()
    assert trace.nodes["end.pos"]["log_prob"].dtype == DTYPE
    out = predict(NET, PARAMS, {"initial.visible": [True], "initial.pos": torch.tensor([[0.1]])})
    assert out.continuous["pos"].mean.dtype == DTYPE


def test_labels_given_to_pyro_condition_are_a_clear_error():
    cond = poutine.condition(effect_model, data={"action": ["tap"]})
    with pytest.raises(ValueError, match=r"site 'action' received \['tap'\].*net.encode"):
        cond(NET, PARAMS, n_rows=1)
    # the documented way
    cond = poutine.condition(effect_model, data=NET.encode({"action": ["tap"]}))
    assert cond(NET, PARAMS, n_rows=1)["action"].tolist() == [2]


def test_model_without_data_runs_one_row():
    values = effect_model(NET, PARAMS)
    assert values["action"].shape == (1,)
    assert effect_model(NET, PARAMS, n_rows=4)["end.pos"].shape == (4, 1)
    with pytest.raises(ValueError, match="at least one row"):
        effect_model(NET, PARAMS, n_rows=0)
    with pytest.raises(ValueError, match="n_rows=2 but the data has 1 rows"):
        effect_model(NET, PARAMS, START, n_rows=2)


def test_render_model_draws_the_network():
    graph = pyro.render_model(effect_model, model_args=(NET, PARAMS, NET.encode(START)))
    source = graph.source
    for edge in (
        'action -> "end.pos"',
        '"initial.visible" -> "end.pos"',
        '"cluster.force" -> "param.force"',
        '"param.force" -> "end.pos"',
        'action -> "end.visible"',
    ):
        assert edge in source
    assert '"end.visible" -> "end.pos"' not in source  # no edges among end sites


def test_discrete_network_renders_too():
    net = EffectNetwork((Discrete("door", ("shut", "open")),), ("wait", "pull"))
    graph = pyro.render_model(effect_model, model_args=(net, random_params(net, 0)))
    assert '"initial.door" -> "end.door"' in graph.source


def default_form_log_density(net, params, data, site, values):
    """log p(data, site = value) per value ``(m, k)``, by the default form: the value
    conditioned through a handler (so nothing ties it to a cell), the cluster enumerated
    and summed out. ``data``: one row."""
    m = values.shape[0]
    rows = net.encode(data).repeat(m)
    conditioned = poutine.condition(effect_model, data={site: values})
    trace = poutine.trace(poutine.enum(conditioned, first_available_dim=-2)).get_trace(
        net, params, rows
    )
    trace.compute_log_prob()
    total = sum(s["log_prob"] for s in trace.nodes.values() if s["type"] == "sample")
    return total.reshape(-1, m).logsumexp(0)


def test_the_collapsed_form_is_the_default_form_with_the_parameter_integrated_out():
    # clusters spilling out of their cells: the value given its cluster is the cluster's
    # Gaussian, untruncated, so integrating it out is the closed-form marginal
    net, params = spilling_network()
    # Gauss-Legendre, 16 nodes on each of 1,400 panels 0.05 N wide over [-30, 40] N (the
    # narrowest integrand, the force given the position, is about 0.4 N wide)
    nodes, weights = np.polynomial.legendre.leggauss(16)
    edges = np.linspace(-30.0, 40.0, 1401)
    half = np.diff(edges)[:, None] / 2
    force = ((edges[:-1, None] + half) + half * nodes).reshape(-1, 1)
    log_w = np.log((half * weights).reshape(-1))
    for x0, y in ((0.0, 0.3), (0.5, 1.4), (-0.4, -0.2), (0.1, 0.1)):
        data = {"initial.pos": [[x0]], "action": ["push"], "end.pos": [[y]]}
        collapsed = float(enumerate_model(net, params, net.encode(data)).log_evidence[0])
        default = default_form_log_density(
            net, params, data, "param.force", torch.tensor(force, dtype=DTYPE)
        )
        integrated = float((default + torch.tensor(log_w, dtype=DTYPE)).logsumexp(0))
        assert integrated == pytest.approx(collapsed, abs=1e-9)

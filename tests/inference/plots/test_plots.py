"""Pictures of fitted networks: each renders to a PNG and shows what the numbers say."""

import math
import sys
from dataclasses import replace
from pathlib import Path

import matplotlib
import numpy as np
import pytest
import torch

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
from effect_networks.inference import fit, fit_em, infer_action, simulate  # noqa: E402
from effect_networks.inference.plots import (  # noqa: E402
    plot_action_posterior,
    plot_clusters,
    plot_network,
    plot_table,
)
from effect_networks.models import Continuous, Discrete, EffectNetwork, Parameter, random_params  # noqa: E402
from effect_networks.models.cpds import TableParams  # noqa: E402
from effect_networks.models.declaration import DTYPE  # noqa: E402
from effect_networks.models.params import NetworkParams  # noqa: E402
from matplotlib.patches import Ellipse, FancyArrowPatch, Rectangle  # noqa: E402

from effect_networks import inference  # noqa: E402

ROOT = Path(__file__).parents[3]


def tap_net(layout="grid", parents=None):
    """A can: visible or not, a position; ``tap`` pushes it with a force in three clusters."""
    return EffectNetwork(
        (Discrete("visible", (False, True)), Continuous("pos", 1)),
        ("remove", "tap"),
        (Parameter("force", 0.0, 9.0, 3, ("tap",), "pos", layout=layout),),
        parents=parents or {},
    )


def place_net():
    """A two-dimensional target in 2 x 3 cells, acting on a two-dimensional place."""
    return EffectNetwork(
        (Continuous("place", 2, initial=False),),
        ("put",),
        (Parameter("target", (0.0, 0.0), (2.0, 3.0), (2, 3), ("put",), "place"),),
    )


def uniform_clusters(net, params):
    """``params`` with the clusters of ``tap`` equally likely (every cluster well drawn)."""
    cpds = dict(params.cpds)
    c = net.mixture("force").parameter.n_clusters
    probs = torch.full((len(net.actions), c), 1.0 / c, dtype=DTYPE)
    probs[0] = torch.nn.functional.one_hot(torch.tensor(0), c)  # remove: pinned on 0
    cpds["cluster.force"] = TableParams(probs, params["cluster.force"].n)
    return NetworkParams(cpds, params.pseudo_count, net)


def rendered(ax, tmp_path):
    path = tmp_path / "plot.png"
    ax.figure.savefig(path)
    plt.close(ax.figure)
    assert path.stat().st_size > 0
    return ax


def ellipse_covariance(e: Ellipse, sigma: float) -> np.ndarray:
    """The covariance an ellipse stands for as the ``sigma`` contour."""
    t = math.radians(e.angle)
    rotation = np.array([[math.cos(t), -math.sin(t)], [math.sin(t), math.cos(t)]])
    axes = np.diag([(e.width / (2 * sigma)) ** 2, (e.height / (2 * sigma)) ** 2])
    return rotation @ axes @ rotation.T


# ------------------------------------------------------------------------------ the graph
@pytest.mark.parametrize("custom", [False, True])
def test_the_graph_draws_one_arrow_per_parent_link(custom, tmp_path):
    parents = {"end.visible": ("initial.visible", "action")} if custom else None
    net = tap_net(parents=parents)
    ax = rendered(plot_network(net), tmp_path)
    # Fig. 1: every initial site and the action into every end site; the parameter:
    # action -> cluster -> value, both into the feature it acts on
    initial, end = ("initial.visible", "initial.pos"), ("end.visible", "end.pos")
    links = {(i, e) for i in initial for e in end} | {("action", e) for e in end}
    links |= {
        ("action", "cluster.force"),
        ("cluster.force", "param.force"),
        ("cluster.force", "end.pos"),
        ("param.force", "end.pos"),
    }
    if custom:
        links.remove(("initial.pos", "end.visible"))
    arrows = [p for p in ax.patches if isinstance(p, FancyArrowPatch)]
    assert len(arrows) == len(links) == (9 if custom else 10)
    assert {tuple(a.get_gid().split("->")) for a in arrows} == links
    assert sorted(t.get_text() for t in ax.texts) == sorted(s.name for s in net.sites)


def test_the_graph_boxes_discrete_and_continuous_sites_differently(tmp_path):
    net = tap_net()
    ax = rendered(plot_network(net), tmp_path)
    style = {t.get_text(): type(t.get_bbox_patch().get_boxstyle()).__name__ for t in ax.texts}
    assert {style[s.name] for s in net.sites if s.discrete} == {"Square"}
    assert {style[s.name] for s in net.sites if not s.discrete} == {"Round"}


def test_end_sites_with_end_parents_sit_to_the_right_of_them(tmp_path):
    net = EffectNetwork(
        (Discrete("a", (0, 1)), Discrete("b", (0, 1))),
        ("go",),
        parents={"end.b": ("initial.b", "action", "end.a")},
    )
    ax = rendered(plot_network(net), tmp_path)
    x = {t.get_text(): t.get_position()[0] for t in ax.texts}
    assert x["initial.a"] < x["action"] < x["end.a"] < x["end.b"]


def test_every_arrow_stops_at_the_edge_of_its_boxes_on_the_first_draw(tmp_path):
    """No arrow (its head included) reaches into the box of its parent or its child. A
    box takes its place as it is drawn and an arrow is cut by its boxes when it is drawn,
    so the arrows must come after the boxes: drawn before them, on a figure's first draw
    they ran to the boxes' centres and their heads lay hidden under the child's box."""
    net = tap_net()
    ax = plot_network(net)
    ax.figure.savefig(tmp_path / "graph.png")  # one draw, no layout pass before it
    renderer = ax.figure.canvas.get_renderer()
    boxes = {t.get_text(): t.get_bbox_patch().get_window_extent(renderer) for t in ax.texts}
    for arrow in (p for p in ax.patches if isinstance(p, FancyArrowPatch)):
        points = ax.transData.transform(arrow.get_path().vertices)
        for site in arrow.get_gid().split("->"):
            box = boxes[site]
            inside = (
                (box.x0 + 1 < points[:, 0])
                & (points[:, 0] < box.x1 - 1)
                & (box.y0 + 1 < points[:, 1])
                & (points[:, 1] < box.y1 - 1)
            )
            assert not inside.any(), (arrow.get_gid(), site)
    arrows = [p.get_zorder() for p in ax.patches if isinstance(p, FancyArrowPatch)]
    assert min(arrows) > max(t.get_zorder() for t in ax.texts)
    plt.close(ax.figure)


# ------------------------------------------------------------------------------ a table
def test_a_table_is_drawn_by_its_labels(tmp_path):
    net = tap_net(parents={"end.visible": ("initial.visible", "action")})
    params = random_params(net, 0)
    ax = rendered(plot_table(net, params, "end.visible"), tmp_path)
    assert [t.get_text() for t in ax.get_xticklabels()] == ["False", "True"]
    rows = [t.get_text() for t in ax.get_yticklabels()]
    assert rows == ["False, remove", "False, tap", "True, remove", "True, tap"]
    assert ax.get_ylabel() == "initial.visible, action"
    image = ax.images[0].get_array()
    probs = params["end.visible"].probs
    for i, row in enumerate(rows):
        visible, action = row.split(", ")
        expected = probs[int(visible == "True"), net.actions.index(action)]
        np.testing.assert_allclose(image[i], expected.numpy())
    assert len(ax.texts) == 4 * 2  # small: every probability written in its cell


def test_a_root_table_and_a_cluster_table(tmp_path):
    net = tap_net()
    params = random_params(net, 1)
    ax = rendered(plot_table(net, params, "action"), tmp_path)
    assert [t.get_text() for t in ax.get_xticklabels()] == ["remove", "tap"]
    np.testing.assert_allclose(ax.images[0].get_array()[0], params["action"].probs.numpy())
    ax = rendered(plot_table(net, params, "cluster.force", annotate=False), tmp_path)
    assert [t.get_text() for t in ax.get_xticklabels()] == ["0", "1", "2"]
    assert [t.get_text() for t in ax.get_yticklabels()] == ["remove", "tap"]
    assert len(ax.texts) == 0


def test_a_table_refuses_an_unknown_site_and_a_site_that_is_no_table():
    net = tap_net()
    params = random_params(net, 0)
    with pytest.raises(ValueError, match="'end.door' does not exist"):
        plot_table(net, params, "end.door")
    with pytest.raises(ValueError, match="'end.pos' has kind 'linear_gaussian', not a table"):
        plot_table(net, params, "end.pos")
    with pytest.raises(ValueError, match="'end.visible' has kind 'softmax'"):
        plot_table(net, params, "end.visible")


# ------------------------------------------------------------------------------ clusters
def test_grid_intervals_are_the_cells_own_mean_and_spread(tmp_path):
    """Under the grid layout each cluster's Gaussian is its cell's rows' mean and
    variance (no pseudo-count): the interval's centre and width say so."""
    net = tap_net()
    rows = simulate(net, uniform_clusters(net, random_params(net, 2)), 600, seed=3)
    params = fit(net, rows, pseudo_count=0.0).params
    ax = rendered(plot_clusters(net, params, "force", rows), tmp_path)
    boxes = [p for p in ax.patches if isinstance(p, Rectangle) and p is not ax.patch]
    assert len(boxes) == 3 * 2
    force = np.asarray(rows["param.force"])[:, 0]
    used = ~np.isnan(force)
    cell = np.asarray(rows["cluster.force"])[used]
    for c in range(3):
        inside = force[used][cell == c]
        one_sigma = boxes[2 * c]
        centre = one_sigma.get_x() + one_sigma.get_width() / 2
        assert centre == pytest.approx(inside.mean(), rel=1e-9)
        assert one_sigma.get_width() / 2 == pytest.approx(inside.std(), rel=1e-6)
        assert boxes[2 * c + 1].get_width() == pytest.approx(2 * one_sigma.get_width())
    assert [t.get_text() for t in ax.get_yticklabels()] == ["rows", "0", "1", "2"]
    (rug,) = [line for line in ax.lines if line.get_marker() == "|"]
    assert len(rug.get_xdata()) == int(used.sum())
    assert len([line for line in ax.lines if line.get_gid() == "cell edge"]) == 3 + 1


@pytest.mark.parametrize("sigmas", [(1.0,), (1.0, 2.0)])
def test_adaptive_clusters_give_one_interval_per_cluster_and_sigma(sigmas, tmp_path):
    net = tap_net("adaptive", parents={"end.visible": ("initial.visible", "action")})
    rows = simulate(net, uniform_clusters(net, random_params(net, 4)), 300, seed=5)
    params = fit_em(net, rows, steps=5).params
    ax = rendered(plot_clusters(net, params, "force", sigmas=sigmas), tmp_path)
    boxes = [p for p in ax.patches if isinstance(p, Rectangle)]
    assert len(boxes) == 3 * len(sigmas)
    centres = [b.get_x() + b.get_width() / 2 for b in boxes[:: len(sigmas)]]
    np.testing.assert_allclose(centres, params["param.force"].bias[:, 0].numpy())
    assert not [line for line in ax.lines if line.get_gid() == "cell edge"]  # no cells


def test_two_dimensional_clusters_are_ellipses_of_their_cells_covariance(tmp_path):
    net = place_net()
    truth = random_params(net, 6)
    cpds = dict(truth.cpds)
    cpds["cluster.target"] = TableParams(
        torch.full((1, 6), 1 / 6, dtype=DTYPE), truth["cluster.target"].n
    )
    rows = simulate(net, NetworkParams(cpds, 0.01, net), 900, seed=7)
    params = fit(net, rows, pseudo_count=0.0).params
    ax = rendered(plot_clusters(net, params, "target", rows), tmp_path)
    ellipses = [p for p in ax.patches if isinstance(p, Ellipse)]
    assert len(ellipses) == 6 * 2
    target = np.asarray(rows["param.target"])
    cell = np.asarray(rows["cluster.target"])
    for c in range(6):
        inside = target[cell == c]
        e = ellipses[2 * c]
        np.testing.assert_allclose(e.center, inside.mean(0), rtol=1e-9)
        np.testing.assert_allclose(
            ellipse_covariance(e, 1.0), np.cov(inside.T, bias=True), rtol=1e-6, atol=1e-12
        )
        np.testing.assert_allclose(
            ellipse_covariance(ellipses[2 * c + 1], 2.0), ellipse_covariance(e, 1.0), rtol=1e-9
        )
    assert ax.collections[0].get_offsets().shape[0] == len(target)
    swapped = rendered(plot_clusters(net, params, "target", dims=(1, 0)), tmp_path)
    assert swapped.get_xlabel() == "param.target[1]"
    assert ellipses[0].width == pytest.approx([p for p in swapped.patches][0].width)


@pytest.mark.parametrize("layout", ["grid", "adaptive"])
def test_the_joint_with_the_feature_matches_draws_from_the_model(layout, tmp_path):
    """The ellipse of (force, end position) per cluster against the mean and covariance
    of many rows drawn from the model with that action and initial state; the position
    leans on the force (slope 3), so the two are strongly correlated."""
    net = tap_net(layout)
    params = uniform_clusters(net, random_params(net, 8))
    pos = params["end.pos"]
    weight = pos.weight.clone()
    weight[..., -1] = 3.0
    params = NetworkParams({**params.cpds, "end.pos": replace(pos, weight=weight)}, 0.01, net)
    given = {"initial.visible": True, "initial.pos": [0.4]}
    ax = plot_clusters(net, params, "force", feature="pos", given=given, sigmas=(1.0,))
    rendered(ax, tmp_path)
    ellipses = [p for p in ax.patches if isinstance(p, Ellipse)]
    assert len(ellipses) == 3
    draws = simulate(net, params, 6000, {"action": "tap", **given}, seed=9)
    cluster = np.asarray(draws["cluster.force"])
    both = np.concatenate([draws["param.force"].numpy(), draws["end.pos"].numpy()], 1)
    for c, e in enumerate(ellipses):
        inside = both[cluster == c]
        assert len(inside) > 1500
        cov = np.cov(inside.T)
        spread = np.sqrt(np.outer(np.diag(cov), np.diag(cov)))
        assert abs(cov[0, 1]) > 0.5 * spread[0, 1]
        error = 4 * np.sqrt(np.diag(cov) / len(inside))
        assert np.all(np.abs(np.asarray(e.center) - inside.mean(0)) < error), (e.center, c)
        drawn = ellipse_covariance(e, 1.0)
        assert np.all(np.abs(drawn - cov) < 0.1 * spread), (drawn, cov, c)


def test_the_joint_draws_the_rows_of_the_given_action_and_states(tmp_path):
    net = tap_net(parents={"end.pos": ("initial.visible", "action")})
    rows = simulate(net, uniform_clusters(net, random_params(net, 10)), 400, seed=11)
    params = fit(net, rows).params
    ax = plot_clusters(net, params, "force", rows, feature="pos", given={"initial.visible": False})
    rendered(ax, tmp_path)
    chosen = [
        a == "tap" and not v for a, v in zip(rows["action"], rows["initial.visible"], strict=True)
    ]
    points = ax.collections[0].get_offsets()
    assert points.shape[0] == sum(chosen) > 0
    np.testing.assert_allclose(points[:, 1], rows["end.pos"].numpy()[chosen, 0])
    assert ax.get_xlabel() == "param.force[0]" and ax.get_ylabel() == "end.pos[0]"


@pytest.mark.parametrize(
    ("layout", "clusters"), [("grid", False), ("grid", True), ("adaptive", False)]
)
def test_the_rows_move_to_the_given_inputs_along_the_fitted_slope(layout, clusters, tmp_path):
    """Rows made by hand, ``pos' = 2 pos + 0.5 force + noise``: drawn for an initial
    position of 0.5, each row sits where its force would have left a can from 0.5 (each
    row's cluster read from the rows where they give it)."""
    net = tap_net(layout, parents={"end.visible": ("initial.visible", "action")})
    g = np.random.default_rng(0)
    n = 600
    action = g.choice(net.actions, n)
    visible = g.random(n) < 0.5
    pos = g.uniform(-1.0, 1.0, (n, 1))
    force = np.where(action[:, None] == "tap", g.uniform(0.0, 9.0, (n, 1)), np.nan)
    end = 2 * pos + 0.5 * np.nan_to_num(force) + g.normal(0.0, 0.01, (n, 1))
    rows = {
        "initial.visible": visible,
        "initial.pos": pos,
        "action": action,
        "param.force": force,
        "end.visible": visible,
        "end.pos": end,
    }
    if clusters:
        rows["cluster.force"] = net.mixture("force").cells(
            torch.as_tensor(force), torch.as_tensor((action == "tap").astype(int))
        )
    params = (fit(net, rows) if layout == "grid" else fit_em(net, rows, steps=10)).params
    given = {"initial.visible": True, "initial.pos": [0.5]}
    ax = plot_clusters(net, params, "force", rows, feature="pos", given=given)
    rendered(ax, tmp_path)
    points = ax.collections[0].get_offsets()
    chosen = (action == "tap") & visible
    assert points.shape[0] == chosen.sum() > 100
    np.testing.assert_allclose(points[:, 0], force[chosen, 0])
    np.testing.assert_allclose(points[:, 1], 2 * 0.5 + 0.5 * force[chosen, 0], atol=0.06)
    assert np.abs(points[:, 1] - end[chosen, 0]).max() > 0.5  # they did move


def test_clusters_refuse_what_they_cannot_draw():
    net = tap_net()
    params = random_params(net, 0)
    with pytest.raises(ValueError, match="unknown parameter 'speed'"):
        plot_clusters(net, params, "speed")
    with pytest.raises(ValueError, match="feature 'visible'.*continuous sites"):
        plot_clusters(net, params, "force", feature="visible")
    with pytest.raises(ValueError, match=r"depends on \['initial.visible', 'initial.pos'\]"):
        plot_clusters(net, params, "force", feature="pos")
    with pytest.raises(ValueError, match=r"given names \['end.visible'\]"):
        plot_clusters(
            net, params, "force", feature="pos", given={"initial.pos": [0.0], "end.visible": True}
        )
    with pytest.raises(ValueError, match="'initial.visible': value 3 is not one of its states"):
        plot_clusters(
            net, params, "force", feature="pos", given={"initial.visible": 3, "initial.pos": [0.0]}
        )
    with pytest.raises(ValueError, match="'initial.pos' has 2 numbers"):
        plot_clusters(
            net,
            params,
            "force",
            feature="pos",
            given={"initial.visible": True, "initial.pos": [0.0, 1.0]},
        )
    with pytest.raises(ValueError, match="action 'remove' does not use parameter 'force'"):
        plot_clusters(
            net,
            params,
            "force",
            feature="pos",
            given={"action": "remove", "initial.visible": True, "initial.pos": [0.0]},
        )
    with pytest.raises(ValueError, match=r"dims \(0, 1\): feature 'pos' has dimensions 0..0"):
        plot_clusters(net, params, "force", feature="pos", dims=(0, 1))
    place = place_net()
    with pytest.raises(ValueError, match=r"dims \(0, 2\): parameter 'target' has dimensions"):
        plot_clusters(place, random_params(place, 0), "target", dims=(0, 2))


# ------------------------------------------------------------------------------ actions
def test_action_bars_are_the_posterior(tmp_path):
    net = tap_net()
    params = random_params(net, 12)
    evidence = {
        "initial.visible": [True, False],
        "initial.pos": [[0.0], [0.5]],
        "end.visible": [False, False],
        "end.pos": [[0.3], [2.0]],
    }
    posterior = infer_action(net, params, evidence)
    for row in (0, 1):
        ax = rendered(plot_action_posterior(posterior, row=row), tmp_path)
        assert [t.get_text() for t in ax.get_xticklabels()] == list(net.actions)
        heights = [bar.get_height() for bar in ax.patches if isinstance(bar, Rectangle)]
        np.testing.assert_allclose(heights, posterior.probs[row].numpy())
        assert sum(heights) == pytest.approx(1.0)
    compiled = inference.compile(net, params).infer_action(evidence)
    ax = rendered(plot_action_posterior(compiled, row=1), tmp_path)
    heights = [bar.get_height() for bar in ax.patches if isinstance(bar, Rectangle)]
    np.testing.assert_allclose(heights, posterior.probs[1].numpy(), atol=1e-12)
    ax = rendered(plot_action_posterior(posterior, actions=["tap", "remove"]), tmp_path)
    assert [t.get_text() for t in ax.get_xticklabels()] == ["tap", "remove"]
    heights = [bar.get_height() for bar in ax.patches if isinstance(bar, Rectangle)]
    np.testing.assert_allclose(heights, posterior.probs[0].flip(0).numpy())


def test_action_bars_refuse_an_unknown_action_or_row():
    net = tap_net()
    posterior = infer_action(
        net, random_params(net, 0), {"initial.pos": [0.0], "end.visible": True}
    )
    with pytest.raises(ValueError, match=r"unknown actions \['throw'\]"):
        plot_action_posterior(posterior, actions=["throw"])
    with pytest.raises(ValueError, match="row 3 is not a row of this posterior, which has 1"):
        plot_action_posterior(posterior, row=3)


# ------------------------------------------------------------------------------ around them
def test_every_function_draws_into_the_axes_it_is_given(tmp_path):
    net = tap_net(parents={"end.visible": ("initial.visible", "action")})
    params = random_params(net, 0)
    posterior = infer_action(net, params, {"initial.pos": [0.0], "end.visible": True})
    fig, axes = plt.subplots(1, 4)
    assert plot_network(net, ax=axes[0]) is axes[0]
    assert plot_table(net, params, "end.visible", ax=axes[1]) is axes[1]
    assert plot_clusters(net, params, "force", ax=axes[2]) is axes[2]
    assert plot_action_posterior(posterior, ax=axes[3]) is axes[3]
    rendered(axes[0], tmp_path)
    from effect_networks.inference.plots import plot_plan

    fig, axes = plt.subplots(1, 2)
    route = door_plan(horizon=2)
    assert plot_plan(route, ax=axes[0]) is axes[0]
    assert plot_plan(route, ax=axes[1], show="path") is axes[1]
    rendered(axes[0], tmp_path)


def test_the_package_offers_the_module_and_no_names_of_it():
    """``inference.plots`` is there; importing ``inference`` loads no matplotlib."""
    import subprocess

    assert inference.plots.plot_network is plot_network
    # the package re-exports each picture from its module
    from effect_networks.inference.plots import graph, plans, posteriors, tables

    assert inference.plots.plot_plan is plans.plot_plan
    assert inference.plots.plot_demonstration is posteriors.plot_demonstration
    assert inference.plots.plot_table is tables.plot_table and graph.plot_network is plot_network
    assert not {"plot_network", "plot_table", "plot_clusters"} & set(inference.__all__)
    code = "import sys, inference; print('matplotlib' in sys.modules)"
    out = subprocess.run(
        [sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, check=True
    )
    assert out.stdout.strip() == "False"


def test_demonstration_heat_map_shows_the_posterior_and_the_sequence(tmp_path):
    from effect_networks.inference import explain
    from effect_networks.inference.plots import plot_demonstration

    net = tap_net()
    params = random_params(net, 3)
    demo = [{"visible": True, "pos": [0.0]}, {"visible": None, "pos": [0.4]}, {"pos": [0.1]}]
    result = explain(net, params, demo)
    ax = rendered(plot_demonstration(result), tmp_path)
    image = ax.get_images()[0].get_array()
    np.testing.assert_allclose(np.asarray(image), result.probs[0].numpy().T)
    line = ax.get_lines()[0]
    assert list(line.get_ydata()) == result.best[0].tolist()
    assert [t.get_text() for t in ax.get_yticklabels()] == list(net.actions)
    with pytest.raises(ValueError, match="row 1 is not a demonstration"):
        plot_demonstration(result, row=1)


# ------------------------------------------------------------------------------ a plan
def door_plan(horizon=3):
    """The door world of docs/planning.md: unlock, then push, opens a locked door."""
    from effect_networks.inference import plan

    net = EffectNetwork(
        (Discrete("door", ("closed", "open")), Discrete("lock", ("locked", "unlocked"))),
        ("unlock", "push", "wait"),
    )
    rows = {k: [] for k in ("initial.door", "initial.lock", "action", "end.door", "end.lock")}
    for door in ("closed", "open"):
        for lock in ("locked", "unlocked"):
            for action in net.actions:
                end_lock = "unlocked" if action == "unlock" else lock
                opens = action == "push" and door == "closed" and lock == "unlocked"
                end = (door, lock, action, "open" if opens else door, end_lock)
                for key, value in zip(rows, end, strict=True):
                    rows[key] += [value] * 5
    params = fit(net, rows).params
    return plan(net, params, ("closed", "locked"), {"door": "open"}, horizon=horizon)


def test_the_policy_grid_shows_each_states_action_and_chance(tmp_path):
    from effect_networks.inference.plots import plot_plan

    route = door_plan(horizon=3)
    ax = rendered(plot_plan(route), tmp_path)
    space = route.model.space
    assert ax.get_xlabel() == "actions left" and ax.get_ylabel() == "door, lock"
    assert [t.get_text() for t in ax.get_xticklabels()] == ["3", "2", "1"]
    assert [t.get_text() for t in ax.get_yticklabels()] == [", ".join(s) for s in space.states]
    texts = {
        (round(t.get_position()[1]), round(t.get_position()[0])): t.get_text() for t in ax.texts
    }
    assert len(ax.texts) == len(space) * 3 == len(texts)
    image = np.ma.asarray(ax.get_images()[0].get_array())
    for i, state in enumerate(space.states):
        for j, left in enumerate((3, 2, 1)):
            action = route.action(state, left)
            if state[0] == "open":  # the goal
                assert texts[i, j] == "goal" and image.mask[i, j]
            else:
                chance = route.probability(state, left)
                assert texts[i, j] == f"{action}\n{chance:.2f}"
                assert route.model.actions[int(image[i, j])] == action
    # the locked door needs both actions: with one left it cannot open
    assert texts[space.index_of(("closed", "locked")), 2].endswith("0.00")


def test_the_path_marks_each_state_and_names_each_action(tmp_path):
    from effect_networks.inference.plots import plot_plan

    route = door_plan(horizon=3)
    ax = rendered(plot_plan(route, show="path"), tmp_path)
    assert route.path[1::2] == ("unlock", "push")
    (line,) = ax.get_lines()
    space = route.model.space
    assert list(line.get_ydata()) == [space.index_of(s) for s in route.path[::2]]
    assert list(line.get_xdata()) == [0, 1, 2]
    assert [t.get_text() for t in ax.texts] == ["unlock", "push"]
    assert ax.get_xlabel() == "step" and f"{route.path_probability:.3g}" in ax.get_title()


def test_an_exact_plan_is_drawn_by_the_labels_given(tmp_path):
    from effect_networks.inference.plots import plot_plan
    from effect_networks.inference.sequences.dynamic_programming import exact_plan

    # two states, one action that moves 0 -> 1 surely; the goal is state 1
    probs = torch.tensor([[[0.0, 1.0]], [[0.0, 1.0]]], dtype=DTYPE)
    solved = exact_plan(probs, 1, horizon=2)
    ax = rendered(plot_plan(solved, states=["far", "near"], actions=["step"]), tmp_path)
    assert [t.get_text() for t in ax.get_yticklabels()] == ["far", "near"]
    assert ax.get_ylabel() == "state"
    # an ExactPlan knows no goal: every cell shows the action and its chance
    assert [t.get_text() for t in ax.texts] == ["step\n1.00"] * 4
    with pytest.raises(ValueError, match="ExactPlan has no path"):
        plot_plan(solved, show="path")
    with pytest.raises(ValueError, match="states names 3 states; the plan has 2"):
        plot_plan(solved, states=["a", "b", "c"])
    with pytest.raises(ValueError, match="show must be one of"):
        plot_plan(door_plan(), show="grid")
    plt.close("all")

"""``explain`` against brute force over every action sequence and every latent state path.

The oracle enumerates, for a demonstration, every assignment of the actions, the latent
parts of every state and every unobserved outcome, multiplies the network's fitted
table entries itself (numpy, :func:`log_table`), and sums or maximises; with continuous
features (whose step densities it does not rebuild) it still enumerates every path and
sequence, reading each fully observed step's probability from the traced model.
"""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
import torch
from effect_networks.inference import fit, infer_action
from effect_networks.inference.exact.enumeration import over_row_chunks
from effect_networks.inference.sequences.demonstration import simulate_demonstrations
from effect_networks.inference.sequences.explanation import Explanation, explain
from effect_networks.models import Continuous, Discrete, EffectNetwork, random_params
from effect_networks.models.can_pyramid import can_network
from effect_networks.models.declaration import DTYPE
from hypothesis import given, settings
from hypothesis import strategies as st

from tests.helpers import discrete_network
from tests.inference.sequences.demonstration_worlds import OUTCOME_NET, PLAIN_NET, uniform_prior
from tests.networks import README_NET


def log_table(net, params, site: str, values: dict) -> float:
    """``log p(site = values[site] | its parents)`` read off the fitted table."""
    cpd = net.cpd(site)
    index = tuple(values[p] for p in cpd.parents) + (values[site],)
    return math.log(float(params[site].probs[index]))


def brute_force(net, params, demo, prior=None, space=None):
    """Every path's log-joint for an all-discrete demonstration (a list of mappings
    feature -> label or None): ``{(actions, states): log p}`` with ``states`` the full
    discrete states (outcomes summed out where not observed), given state 0's
    observation; the start state drawn from the network's initial tables."""
    state = [f for f in net.features if f.initial]
    outcome = [f for f in net.features if not f.initial]
    a = len(net.actions)
    prior = np.full(a, 1 / a) if prior is None else np.asarray(prior)

    def options(f, value):
        return range(f.cardinality) if value is None else [f.states.index(value)]

    per_time = [
        [
            s
            for s in itertools.product(*[options(f, x.get(f.name)) for f in state])
            if space is None or s in space
        ]
        for x in demo
    ]
    start = {}
    for s in per_time[0]:
        v = {f"initial.{f.name}": i for f, i in zip(state, s, strict=True)}
        start[s] = sum(log_table(net, params, site, v) for site in v)
    norm = np.logaddexp.reduce(list(start.values()))
    paths = {}
    for states in itertools.product(*per_time):
        for actions in itertools.product(range(a), repeat=len(demo) - 1):
            total = start[states[0]] - norm
            for t, act in enumerate(actions):
                v = {f"initial.{f.name}": i for f, i in zip(state, states[t], strict=True)}
                v |= {f"end.{f.name}": i for f, i in zip(state, states[t + 1], strict=True)}
                v["action"] = act
                step = np.log(prior[act])
                step += sum(log_table(net, params, f"end.{f.name}", v) for f in state)
                seen = [f for f in outcome if demo[t + 1].get(f.name) is not None]
                for f in seen:
                    v[f"end.{f.name}"] = f.states.index(demo[t + 1][f.name])
                    step += log_table(net, params, f"end.{f.name}", v)
                total += step
            paths[(actions, states)] = total
    return paths


def check_against(net, params, demo, result: Explanation, prior=None, space=None):
    paths = brute_force(net, params, demo, prior, space)
    logs = np.array(list(paths.values()))
    log_likelihood = np.logaddexp.reduce(logs)
    assert float(result.log_likelihood[0]) == pytest.approx(log_likelihood, abs=1e-9)
    steps = len(demo) - 1
    post = np.zeros((steps, len(net.actions)))
    for (actions, _), lp in paths.items():
        for t, act in enumerate(actions):
            post[t, act] += math.exp(lp - log_likelihood)
    assert np.allclose(result.probs[0].numpy(), post, atol=1e-9)
    assert np.allclose(result.probs.sum(-1).numpy(), 1.0, atol=1e-12)
    # Viterbi: the jointly most probable (actions, states) path
    (actions, states), top = max(paths.items(), key=lambda kv: kv[1])
    space = result.states
    got_states = tuple(space[s] for s in result.path[0].tolist())
    want_states = tuple(
        tuple(f.states[i] for f, i in zip([f for f in net.features if f.initial], s, strict=True))
        for s in states
    )
    got = paths[(tuple(result.best[0].tolist()), tuple(_indices(net, got_states)))]
    assert got == pytest.approx(top, abs=1e-9)  # the path found is a most probable one
    runner_up = sorted(logs)[-2] if len(logs) > 1 else -np.inf
    if top - runner_up > 1e-6:  # no tie: the very path
        assert result.best[0].tolist() == list(actions)
        assert got_states == want_states


def _indices(net, labels):
    state = [f for f in net.features if f.initial]
    return [tuple(f.states.index(x) for f, x in zip(state, s, strict=True)) for s in labels]


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 10_000), data=st.data())
def test_matches_brute_force_on_partly_observed_demonstrations(seed, data):
    drawn = discrete_network(
        data.draw(st.lists(st.integers(2, 3), min_size=1, max_size=2)), data.draw(st.integers(1, 3))
    )
    net = data.draw(st.sampled_from([OUTCOME_NET, PLAIN_NET, drawn]))
    params = random_params(net, seed)
    steps = data.draw(st.integers(1, 3))
    demo = []
    for t in range(steps + 1):
        state = {}
        for f in net.features:
            if not f.initial and t == 0:
                continue
            state[f.name] = data.draw(st.none() | st.sampled_from(f.states))
        demo.append(state)
    result = explain(net, params, demo)
    check_against(net, params, demo, result)
    # implausible: p(step t's observed end | everything observed before it) below the
    # threshold; the oracle's ratio of the prefixes' likelihoods
    t = data.draw(st.integers(0, steps - 1))
    prefix = [
        np.logaddexp.reduce(list(brute_force(net, params, demo[: u + 1]).values()))
        for u in (t, t + 1)
    ]
    predictive = math.exp(prefix[1] - prefix[0]) if t else math.exp(prefix[1])
    for below, flagged in [(predictive * 0.99, False), (predictive * 1.01, True)]:
        if 0 < below < 1:
            again = explain(net, params, demo, implausible_below=below)
            assert bool(again.implausible[0, t]) == flagged


def test_a_given_prior_replaces_the_uniform_one():
    params = random_params(OUTCOME_NET, 3)
    demo = [
        {"door": "shut", "light": None},
        {"door": None, "light": "on", "creak": True},
        {"door": "open", "light": None, "creak": None},
    ]
    prior = [0.7, 0.1, 0.2]
    result = explain(
        OUTCOME_NET, params, demo, prior=dict(zip(OUTCOME_NET.actions, prior, strict=True))
    )
    check_against(OUTCOME_NET, params, demo, result, prior)
    # an action of prior 0 is ruled out exactly (the model's own tables keep it at eps)
    without = [0.5, 0.0, 0.5]
    result = explain(OUTCOME_NET, params, demo, prior=without)
    with np.errstate(divide="ignore"):
        check_against(OUTCOME_NET, params, demo, result, without)
    assert not result.prob("flip").any()


def test_fully_observed_states_are_per_step_emulation():
    """Each step's posterior, flag and probability are infer_action's under the same
    (uniform) action prior."""
    net = OUTCOME_NET
    params = random_params(net, 11)
    demo = [
        {"door": "locked", "light": "off"},
        {"door": "shut", "light": "off", "creak": True},
        {"door": "open", "light": "on", "creak": False},
        {"door": "open", "light": "on", "creak": True},
    ]
    result = explain(net, params, demo, implausible_below=0.05)
    uniform = uniform_prior(net, params)
    log_likelihood = 0.0
    for t in range(3):
        ev = {f"initial.{f}": [demo[t][f]] for f in ("door", "light")}
        ev |= {f"end.{f}": [v] for f, v in demo[t + 1].items()}
        step = infer_action(net, uniform, ev, implausible_below=0.05)
        assert torch.allclose(result.probs[0, t], step.probs[0], atol=1e-12)
        assert bool(result.implausible[0, t]) == bool(step.implausible[0])
        start = infer_action(net, uniform, {k: v for k, v in ev.items() if "initial" in k})
        log_likelihood += float(step.log_evidence[0] - start.log_evidence[0])
    assert float(result.log_likelihood[0]) == pytest.approx(log_likelihood, abs=1e-10)
    assert result.path_labels(0) == [{"door": x["door"], "light": x["light"]} for x in demo]


@pytest.mark.filterwarnings("ignore::effect_networks.inference.OutsideTrainingData")
def test_continuous_features_and_a_parameter_reduce_to_emulation():
    """README's network: the position observed at every time, the tap's force never;
    each fully observed step is infer_action's question (the force integrated out)."""
    rng = np.random.default_rng(0)
    params = random_params(README_NET, 5)
    visible = [True, True, False, False]
    position = np.cumsum(rng.normal(0, 0.3, 4))[:, None]
    demo = [{"visible": v, "position": p} for v, p in zip(visible, position, strict=True)]
    result = explain(README_NET, params, demo, implausible_below=0.01)
    uniform = uniform_prior(README_NET, params)
    for t in range(3):
        ev = {
            "initial.visible": [visible[t]],
            "initial.position": [position[t]],
            "end.visible": [visible[t + 1]],
            "end.position": [position[t + 1]],
        }
        step = infer_action(README_NET, uniform, ev, implausible_below=0.01)
        assert torch.allclose(result.probs[0, t], step.probs[0], atol=1e-10)
        assert bool(result.implausible[0, t]) == bool(step.implausible[0])


def step_log_prob(net, params, enc):
    return over_row_chunks(net, params, enc, (), lambda e, *_: e.log_evidence, contracted=True)


def check_two_steps_against_paths(net, result: Explanation, paths: dict, latent: str) -> None:
    """A two-step demonstration's answers against the brute force's ``paths``: (action
    sequence, middle label of ``latent``) -> log p(demonstration, path)."""
    log_likelihood = np.logaddexp.reduce(list(paths.values()))
    assert float(result.log_likelihood[0]) == pytest.approx(log_likelihood, abs=1e-9)
    for t in range(2):
        for i, name in enumerate(net.actions):
            want = sum(
                math.exp(lp - log_likelihood) for (acts, _), lp in paths.items() if acts[t] == name
            )
            assert float(result.probs[0, t, i]) == pytest.approx(want, abs=1e-9)
    (actions, middle), _ = max(paths.items(), key=lambda kv: kv[1])
    assert result.best_names[0] == actions
    assert result.path_labels(0)[1] == {latent: middle}


@pytest.mark.filterwarnings("ignore::effect_networks.inference.OutsideTrainingData")
def test_continuous_latent_path_matches_brute_force():
    """The visible flag latent in the middle state; the oracle enumerates every path and
    action sequence, each step's log p(end, a | start) read off the traced model with
    everything observed."""
    net, params = README_NET, uniform_prior(README_NET, random_params(README_NET, 8))
    position = np.array([[0.1], [0.4], [0.3]])
    demo = [
        {"visible": True, "position": position[0]},
        {"visible": None, "position": position[1]},
        {"visible": False, "position": position[2]},
    ]
    result = explain(net, params, demo)
    flags = (False, True)
    paths = {}
    for middle in flags:
        states = (True, middle, False)
        for actions in itertools.product(net.actions, repeat=2):
            total = 0.0
            for t in range(2):
                given = {"initial.visible": [states[t]], "initial.position": [position[t]]}
                full = given | {
                    "action": [actions[t]],
                    "end.visible": [states[t + 1]],
                    "end.position": [position[t + 1]],
                }
                total += float(step_log_prob(net, params, net.encode(full)))
                total -= float(step_log_prob(net, params, net.encode(given)))
            paths[(actions, middle)] = total
    check_two_steps_against_paths(net, result, paths, "visible")


def test_a_batch_answers_each_demonstration_as_alone():
    net = OUTCOME_NET
    params = random_params(net, 2)
    demos = [
        [
            {"door": "shut", "light": "off"},
            {"door": None, "light": "on", "creak": True},
            {"door": "open", "light": None},
        ],
        [
            {"door": None, "light": "off"},
            {"door": "open", "light": "off", "creak": None},
            {"door": "open", "light": "on", "creak": False},
        ],
    ]
    batch = {
        f.name: np.array([[d[t].get(f.name) for t in range(3)] for d in demos], dtype=object)
        for f in net.features
    }
    together = explain(net, params, batch)
    for i, demo in enumerate(demos):
        alone = explain(net, params, demo)
        assert torch.allclose(together.probs[i], alone.probs[0], atol=1e-12)
        assert together.best_names[i] == alone.best_names[0]
        assert torch.allclose(together.log_likelihood[i], alone.log_likelihood[0], atol=1e-12)
        assert torch.allclose(together.state_probs[i], alone.state_probs[0], atol=1e-12)


def test_state_posterior_sums_to_one_and_fits_the_observations():
    net = OUTCOME_NET
    params = random_params(net, 4)
    demo = [{"door": "shut"}, {"light": "on"}, {}]
    result = explain(net, params, demo)
    assert torch.allclose(result.state_probs.sum(-1), torch.ones(1, 3, dtype=DTYPE))
    door = [s[0] for s in result.states]
    off_door = [i for i, d in enumerate(door) if d != "shut"]
    assert float(result.state_probs[0, 0, off_door].sum()) == 0.0


def test_an_impossible_step_is_flagged():
    """A door world fitted on rows where waiting never changes anything: a wait that
    opens a locked door in between is implausible; the plausible step is not."""
    net = EffectNetwork(
        features=(Discrete("door", ("locked", "open")),), actions=("unlock", "wait")
    )
    rows = {
        "initial.door": ["locked", "locked", "open", "open"] * 50,
        "action": ["unlock", "wait", "unlock", "wait"] * 50,
        "end.door": ["open", "locked", "open", "open"] * 50,
    }
    params = fit(net, rows).params
    demo = [{"door": "open"}, {"door": "locked"}, {"door": "open"}]
    result = explain(net, params, demo, implausible_below=0.01)
    assert result.implausible[0].tolist() == [True, False]


def test_errors_name_what_is_wrong():
    net, params = OUTCOME_NET, random_params(OUTCOME_NET, 0)
    with pytest.raises(ValueError, match="unknown features \\['colour'\\]"):
        explain(net, params, [{"colour": 1}, {}])
    with pytest.raises(ValueError, match="states\\['door'\\].*ajar"):
        explain(net, params, [{"door": "ajar"}, {}])
    with pytest.raises(ValueError, match="creak.*state 0"):
        explain(net, params, [{"creak": True}, {}])
    with pytest.raises(ValueError, match="at least 2 states"):
        explain(net, params, [{"door": "shut"}])
    with pytest.raises(ValueError, match="sum to 1"):
        explain(net, params, [{}, {}], prior=[0.5, 0.5, 0.5])
    with pytest.raises(ValueError, match="'position' is missing"):
        explain(README_NET, random_params(README_NET, 0), [{"visible": True}, {}])


@pytest.mark.filterwarnings("ignore::effect_networks.inference.OutsideTrainingData")
def test_parts_and_chunks_answer_as_one_batch(monkeypatch):
    """The batch read part by part and the step tables row by row: the same answers as all
    at once."""
    import effect_networks.inference.sequences.explanation as module
    import effect_networks.inference.sequences.hidden_steps as steps

    net, params = README_NET, random_params(README_NET, 6)
    states, _ = simulate_demonstrations(net, params, 7, 3, seed=2)
    states["visible"][:, 1] = None
    whole = explain(net, params, states)
    monkeypatch.setattr(module, "TABLE_ELEMENTS", 3 * (1 + 2 + 2) * 2)  # two demonstrations a part
    monkeypatch.setattr(steps, "ROW_CHUNK", len(net.actions))  # one (start, end) pair a read
    parts = explain(net, params, states)
    assert torch.allclose(whole.probs, parts.probs, atol=1e-12)
    assert torch.allclose(whole.log_likelihood, parts.log_likelihood, atol=1e-12)
    assert whole.best_names == parts.best_names
    assert torch.equal(whole.implausible, parts.implausible)
    assert torch.allclose(whole.state_probs, parts.state_probs, atol=1e-12)
    assert torch.equal(whole.path, parts.path)


def test_simulated_demonstrations_are_read_back():
    """A world whose actions each have their own certain effect: every drawn action
    sequence is the most probable one, with posterior near 1."""
    net = EffectNetwork(
        features=(Discrete("door", ("shut", "open")), Discrete("light", ("off", "on"))),
        actions=("open", "close", "flip"),
    )
    rows = {"initial.door": [], "initial.light": [], "action": [], "end.door": [], "end.light": []}
    for door, light, action in itertools.product(("shut", "open"), ("off", "on"), net.actions):
        end_door = {"open": "open", "close": "shut"}.get(action, door)
        end_light = {"off": "on", "on": "off"}[light] if action == "flip" else light
        for site, v in zip(rows, (door, light, action, end_door, end_light), strict=True):
            rows[site] += [v] * 30
    params = fit(net, rows).params
    states, actions = simulate_demonstrations(net, params, 40, 4, seed=3)
    assert states["door"].shape == (40, 5) and actions.shape == (40, 4)
    result = explain(net, params, states)
    # opening an open door and closing a shut one change nothing: both explain it
    same = np.array(result.best_names) == actions
    idle = (states["door"][:, :-1] == states["door"][:, 1:]) & (actions != "flip")
    assert (same | idle).all()
    assert same[~idle].all()
    assert float(result.probs.max(-1).values[torch.from_numpy(~idle)].min()) > 0.9


@pytest.mark.filterwarnings("ignore::effect_networks.inference.OutsideTrainingData")
def test_the_demonstrations_page_runs_and_says_what_its_comments_say():
    """docs/demonstrations.md continues README's quick start: both run, in order."""
    import re
    from pathlib import Path

    import matplotlib

    matplotlib.use("Agg")
    root = Path(__file__).resolve().parents[3]
    block = re.compile(r"^```python\n(.*?)^```", re.S | re.M)
    namespace: dict = {}
    exec(block.findall((root / "README.md").read_text())[0], namespace)  # noqa: S102
    for code in block.findall((root / "docs" / "demonstrations.md").read_text()):
        exec(code, namespace)  # noqa: S102
    assert namespace["steps"] == (("tap", "remove"),)
    tapped = namespace["tapped"][0].tolist()
    assert tapped[0] > 0.99 and tapped[1] < 0.01
    assert namespace["both"].best_names == (("tap", "remove"), ("look", "tap"))
    assert tuple(namespace["both"].state_probs.shape) == (2, 3, 2)
    assert 0.5 < namespace["share"] <= 1


def test_no_demonstrations_give_empty_answers():
    net, params = OUTCOME_NET, random_params(OUTCOME_NET, 0)
    result = explain(net, params, {"door": np.empty((0, 4), dtype=object)})
    assert tuple(result.probs.shape) == (0, 3, 3) and result.best_names == ()
    assert tuple(result.state_probs.shape) == (0, 4, 6)


@pytest.mark.filterwarnings("ignore::effect_networks.inference.OutsideTrainingData")
def test_a_continuous_outcome_seen_at_some_steps_matches_brute_force():
    """An outcome feature (initial=False) observed after the first step, not after the
    second, and the door latent in between: every path and sequence enumerated, each
    step's probability read off the traced model with its start and end given."""
    net = EffectNetwork(
        features=(Discrete("door", ("shut", "open")), Continuous("sound", 1, initial=False)),
        actions=("knock", "push", "wait"),
    )
    params = uniform_prior(net, random_params(net, 4))
    demo = [
        {"door": "shut"},
        {"door": None, "sound": [0.3]},
        {"door": "open", "sound": None},
    ]
    result = explain(net, params, demo)
    paths = {}
    for middle in net.feature("door").states:
        doors = ("shut", middle, "open")
        for actions in itertools.product(net.actions, repeat=2):
            total = 0.0
            for t in range(2):
                given = {"initial.door": [doors[t]]}
                full = given | {"action": [actions[t]], "end.door": [doors[t + 1]]}
                if demo[t + 1].get("sound") is not None:
                    full["end.sound"] = [demo[t + 1]["sound"]]
                total += float(step_log_prob(net, params, net.encode(full)))
                total -= float(step_log_prob(net, params, net.encode(given)))
            paths[(actions, middle)] = total
    check_two_steps_against_paths(net, result, paths, "door")


def test_a_named_state_space_matches_brute_force_over_it():
    """The can network with four configurations, each with its count: 4 states instead of
    the product's 44, the others never entered."""
    net = can_network([0, 1, 3, 7], n_fields=3)
    params = random_params(net, 9)
    space = [(c, bin(c).count("1")) for c in (0, 1, 3, 7)]
    demo = [
        {"config": 7, "count": 3},
        {"config": None, "count": None},
        {"config": None, "count": 1},
        {"config": 0, "count": 0},
    ]
    result = explain(net, params, demo, state_space=space)
    assert result.states == tuple(space)
    index = [tuple(f.states.index(x) for f, x in zip(net.features, s, strict=True)) for s in space]
    check_against(net, params, demo, result, space=index)
    with pytest.raises(ValueError, match="time 1 shows .*no state of the state space"):
        explain(net, params, [demo[0], {"config": 1, "count": 2}], state_space=space)
    with pytest.raises(ValueError, match="feature 'config' has no state 5"):
        explain(net, params, demo, state_space=[(0, 0), (5, 2)])

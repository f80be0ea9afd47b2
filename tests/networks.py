"""The networks and data builders that several test modules share.

Each is built by a test module's checks and read by others; none is a test itself.
"""

from __future__ import annotations

import mpmath
import numpy as np
import torch
from effect_networks.inference.exact.enumeration import enumerate_model
from effect_networks.models import (
    Continuous,
    Discrete,
    EffectNetwork,
    Parameter,
    random_params,
)
from effect_networks.models.declaration import DTYPE
from effect_networks.models.model import effect_model
from hypothesis import strategies as st

# a mixed network: a visibility flag, a 2-D position and a force parameter
NET = EffectNetwork(
    (Discrete("visible", (False, True)), Continuous("pos", 2)),
    ("remove", "tap", "push"),
    (Parameter("force", (0.0,), (10.0,), (3,), ("tap", "push"), "pos"),),
)


# README's network: a softmax end.visible (initial.position is its continuous input), a
# Gaussian end.position, and a force parameter on "tap"
README_NET = EffectNetwork(
    features=(Discrete("visible", (False, True)), Continuous("position", 1)),
    actions=("look", "remove", "tap"),
    parameters=(
        Parameter("force", low=0.0, high=20.0, bins=8, actions=("tap",), affects="position"),
    ),
)


def softmax_oracle(params, index: tuple[int, ...], x: float) -> list:
    """``p(end.visible | discrete parents, initial.position = x)`` in 60-digit arithmetic
    (mpmath numbers, whose exponent does not underflow)."""
    cpd = params["end.visible"]
    w, b = cpd.weight[index].tolist(), cpd.bias[index].tolist()  # (K, 1), (K,)
    with mpmath.workdps(60):
        logits = [
            mpmath.mpf(wk[0]) * mpmath.mpf(x) + mpmath.mpf(bk) for wk, bk in zip(w, b, strict=True)
        ]
        e = [mpmath.exp(v) for v in logits]
        return [v / sum(e) for v in e]


# parameters acting on continuous features, and their joints by hand
PUSH_ACTIONS = ("push", "wait")


# ---------------------------------------------------------------- two parameters, one feature
def sliding():
    force = Parameter("force", 0.0, 4.0, 2, ("push",), "pos")
    angle = Parameter("angle", -1.0, 1.0, 2, ("push",), "pos")
    net = EffectNetwork((Continuous("pos", 1),), PUSH_ACTIONS, (force, angle))
    return net, random_params(net, 7)


def throwing():
    """One aim acting on two continuous features (where the ball lands, how far it
    rolls): an unknown aim couples them."""
    aim = Parameter("aim", 0.0, 2.0, 2, ("throw",), ("land", "roll"))
    net = EffectNetwork(
        (Continuous("land", 2), Continuous("roll", 1)),
        ("throw", "drop"),
        (aim,),
        parents={"end.land": ("initial.land", "action"), "end.roll": ("initial.roll", "action")},
    )
    return net, random_params(net, 5)


def joint_by_hand(params, x_land, x_roll, c):
    """Per cluster ``c`` of the action throw: the joint Gaussian of (end.land, end.roll)
    with the aim integrated out, and the two sites' weights on the aim."""
    land, roll = params["end.land"], params["end.roll"]
    prior = params["param.aim"]
    m, s = prior.bias[c].numpy(), prior.covariance[c].numpy()
    w1, w2 = land.weight[0, c].numpy(), roll.weight[0, c].numpy()  # (2, 3), (1, 2)
    mu1 = land.bias[0, c].numpy() + w1[:, :2] @ x_land + w1[:, 2:] @ m
    mu2 = roll.bias[0, c].numpy() + w2[:, :1] @ x_roll + w2[:, 1:] @ m
    w = np.vstack([w1[:, 2:], w2[:, 1:]])  # (3, 1): both sites' weights on the aim
    noise = np.zeros((3, 3))
    noise[:2, :2], noise[2:, 2:] = land.covariance[0, c].numpy(), roll.covariance[0, c].numpy()
    return np.concatenate([mu1, mu2]), w @ s @ w.T + noise, w, m, s


# a door-and-lock world with noise, for state transitions
DOOR = ("shut", "open")


LOCK = ("off", "on")


NOISE = (0, 1, 2)


def rich_net() -> EffectNetwork:
    """Two state features, the lock's end depending on the door's end and an end-only
    ``noise`` (both latent in a step), a parameter acting on the door (discrete) and a
    continuous feature, and a continuous initial feature the door's softmax reads."""
    return EffectNetwork(
        features=(
            Discrete("door", DOOR),
            Discrete("lock", LOCK),
            Continuous("x", 1),
            Discrete("noise", NOISE, initial=False),
        ),
        actions=("push", "unlock", "wait"),
        parameters=(
            Parameter("force", low=0.0, high=1.0, bins=3, actions=("push",), affects=("door", "x")),
        ),
        parents={"end.lock": ("initial.lock", "action", "end.door", "end.noise")},
    )


def rich_rows(net: EffectNetwork, n: int, seed: int) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    a = rng.choice(net.actions, n)
    door = rng.choice(DOOR, n)
    force = np.where(a[:, None] == "push", rng.uniform(0, 1, (n, 1)), np.nan)
    opened = (a == "push") & (rng.random(n) < np.nan_to_num(force[:, 0]))
    end_door = np.where(opened, "open", door)
    noise = rng.choice(NOISE, n)
    lock = rng.choice(LOCK, n)
    flips = (end_door == "open") ^ (noise == 2)
    return {
        "initial.door": door,
        "initial.lock": lock,
        "initial.x": rng.normal(size=(n, 1)),
        "action": a,
        "param.force": force,
        "end.door": end_door,
        "end.lock": np.where(flips, np.where(lock == "on", "off", "on"), lock),
        "end.x": rng.normal(size=(n, 1)),
        "end.noise": noise,
    }


# a tap world, for EM
def tap_net(bins=3, affects="pos", layout="adaptive"):
    """A tap world: the force of ``tap`` moves the can (and may knock it over)."""
    return EffectNetwork(
        (Discrete("visible", (0, 1)), Continuous("pos", 1, initial=False)),
        ("remove", "tap"),
        (Parameter("force", (0.0,), (10.0,), (bins,), ("tap",), affects, layout=layout),),
    )


def tap_data(net, n=300, seed=0):
    g = torch.Generator().manual_seed(seed)
    a = torch.randint(0, 2, (n,), generator=g)
    vis0 = torch.randint(0, 2, (n,), generator=g)
    force = torch.rand(n, 1, generator=g, dtype=DTYPE) * 10
    force[a == 0] = float("nan")
    f = force.nan_to_num()
    falls = torch.rand(n, generator=g, dtype=DTYPE) < f[:, 0] / 12
    vis1 = torch.where((a == 0) | falls, 0, vis0)
    pos = torch.where(a[:, None] == 1, torch.sqrt(f) + 0.05 * f**2, 0.0)
    pos = pos + 0.1 * torch.randn(n, 1, generator=g, dtype=DTYPE)
    return net.encode_indices(
        {
            "initial.visible": vis0,
            "action": a,
            "param.force": force,
            "end.visible": vis1,
            "end.pos": pos,
        }
    )


# doors, drawers and switches with a handle (a softmax end state)
# ------------------------------------------------------------------ softmax: Newton's method
HANDLE_KINDS, HANDLE_STATES, HANDLE_ACTIONS = (
    ("door", "drawer", "switch"),
    ("closed", "ajar", "open"),
    ("pull", "push", "press"),
)


def handle_world(n=3000, seed=0, parents=None):
    """Doors, drawers and switches, closed, ajar or open: ``end.state`` is a softmax of
    the handle height and the effort per (kind, state, action), 27 configurations.
    ``parents``: more parent sets for the network (the end kind's is its initial kind)."""
    import numpy as np

    net = EffectNetwork(
        (
            Discrete("kind", HANDLE_KINDS),
            Discrete("state", HANDLE_STATES),
            Continuous("handle", 1),
            Continuous("effort", 1),
        ),
        HANDLE_ACTIONS,
        parents={"end.kind": ("initial.kind",)} | (parents or {}),
    )
    rng = np.random.default_rng(seed)
    kind, state, action = (rng.integers(0, 3, n) for _ in range(3))
    handle = rng.normal(1.0, 0.3, n) + 0.2 * kind
    effort = rng.gamma(2.0, 1.0, n)
    strength = np.array([[3.0, 1.0, 0.2], [2.5, 2.0, 0.1], [0.1, 0.5, 4.0]])[kind, action]
    opens = 1 / (1 + np.exp(-(2.0 * (strength - effort) - 0.5 * (handle - 1.2))))
    u = rng.random(n)
    target = np.where(action == 1, 0, 2)  # push closes, pull and press open
    end = np.where(u < opens, target, np.where(u < opens + 0.5 * (1 - opens), 1, state))
    data = {
        "initial.kind": np.array(HANDLE_KINDS)[kind],
        "initial.state": np.array(HANDLE_STATES)[state],
        "initial.handle": handle[:, None],
        "initial.effort": effort[:, None],
        "action": np.array(HANDLE_ACTIONS)[action],
        "end.kind": np.array(HANDLE_KINDS)[kind],
        "end.state": np.array(HANDLE_STATES)[end],
        "end.handle": handle[:, None] + 0.01 * rng.normal(size=(n, 1)),
        "end.effort": effort[:, None] + 0.01 * rng.normal(size=(n, 1)),
    }
    return net, data


# random mixed networks (hypothesis)
@st.composite
def mixed_networks(draw):
    """Discrete and continuous features, and perhaps a parameter that some actions use."""
    features = [
        Discrete(f"d{i}", ("x", "y", "z")[: draw(st.integers(2, 3))])
        for i in range(draw(st.integers(0, 1)))
    ]
    features += [
        Continuous(f"c{i}", draw(st.integers(1, 2))) for i in range(draw(st.integers(1, 2)))
    ]
    actions = tuple(f"a{j}" for j in range(draw(st.integers(2, 3))))
    parameters = ()
    if draw(st.booleans()):
        parameters = (Parameter("p", 0.0, 1.0, draw(st.integers(1, 3)), actions[:1], "c0"),)
    return EffectNetwork(tuple(features), actions, parameters)


# random networks of every kind the toolkit declares (hypothesis): saved and loaded
def same_bits(a: torch.Tensor, b: torch.Tensor) -> bool:
    """Equal dtype, shape and bytes (NaN equal to itself, -0.0 unequal to 0.0)."""
    return (
        a.dtype == b.dtype
        and a.shape == b.shape
        and np.ascontiguousarray(a.numpy()).tobytes() == np.ascontiguousarray(b.numpy()).tobytes()
    )


@st.composite
def networks_of_every_kind(draw):
    """A network of one to three features, each discrete (two or three states) or
    continuous (one or two dimensions), sparse parents drawn by the declaration's rules,
    and perhaps a parameter on a grid or adaptive clusters."""
    n = draw(st.integers(1, 3))
    features = []
    for i in range(n):
        if draw(st.booleans()):
            features.append(Discrete(f"d{i}", tuple(range(draw(st.integers(2, 3))))))
        else:
            features.append(Continuous(f"c{i}", draw(st.integers(1, 2))))
    actions = ("a", "b")
    parents = {}
    for f in features:
        pool = [f"initial.{g.name}" for g in features] + ["action"]
        pool += [
            f"end.{g.name}"
            for g in features
            if isinstance(g, Discrete) and g.name < f.name and g is not f
        ]
        chosen = draw(st.lists(st.sampled_from(pool), unique=True, max_size=3))
        parents[f"end.{f.name}"] = tuple(chosen)
    parameters = ()
    continuous = [f for f in features if isinstance(f, Continuous)]
    if continuous and draw(st.booleans()):
        layout = draw(st.sampled_from(["grid", "adaptive"]))
        parameters = (Parameter("p", 0.0, 4.0, 2, ("a",), continuous[0].name, layout=layout),)
        site = f"end.{continuous[0].name}"
        parents[site] = tuple(dict.fromkeys((*parents[site], "action")))
    return EffectNetwork(tuple(features), actions, parameters, parents=parents)


# tap worlds with missing values, and their marginal loss
def marginal_loss(net, params, rows, masks, l2=0.01, presence=False):
    """Per-row -log p(the observed values), the softmax prior included, and its
    gradient's largest component over every CPD's free tensors. Pyro's TraceEnum_ELBO on
    the model with the masked values latent; with ``presence``, a missing action ranges
    over the actions that use exactly the parameters the row gives: each action given in
    turn (the model enumerated by the queries' machinery), their likelihoods summed."""
    import pyro
    from effect_networks.models.params import NetworkParams
    from pyro.infer import TraceEnum_ELBO

    free = {
        s: {k: t.detach().clone().requires_grad_() for k, t in net.cpd(s).free(params[s]).items()}
        for s in params.cpds
    }
    bound = NetworkParams({s: net.cpd(s).bound(f, params[s]) for s, f in free.items()}, 0.0)

    if presence:
        others = {s: m for s, m in masks.items() if s != "action"}
        data = rows.without(*(m.cluster.site for m in net.mixtures))
        per_action = []
        for a in range(len(net.actions)):
            given = data | net.encode_indices({"action": torch.full((rows.n_rows,), a)})
            log_p = enumerate_model(net, bound, given, masks=others).log_evidence
            agree = masks["action"] == (rows["action"] == a)  # the given action, or...
            for m in net.mixtures:  # ... one that uses exactly the parameters given
                present = ~torch.isnan(rows[m.value.site]).any(-1)
                agree = torch.where(masks["action"], agree, m.uses[a] == present)
            per_action.append(torch.where(agree, log_p, -torch.inf))
        loss = -torch.stack(per_action).logsumexp(0).sum()
    else:

        def model():
            effect_model(net, bound, rows, masks=masks, collapse=True)

        with pyro.validation_enabled(False):
            loss = TraceEnum_ELBO(max_plate_nesting=1).differentiable_loss(model, lambda: None)
    for s, f in free.items():
        for w in net.cpd(s).penalised(f):
            loss = loss + 0.5 * l2 * w.square().sum()
    loss = loss / rows.n_rows
    tensors = [t for f in free.values() for t in f.values()]
    grads = torch.autograd.grad(loss, tensors, allow_unused=True)
    return float(loss.detach()), max(float(g.abs().max()) for g in grads if g is not None)


def tap3_rows(n=300, seed=0, users=("tap", "push")):
    """Remove, tap and push: the force of tap and push moves the can differently (and
    may knock it over). Masks: the action missing in 30 % of the rows, the initial
    visibility in 20 %."""
    net = EffectNetwork(
        (Discrete("visible", (0, 1)), Continuous("pos", 1, initial=False)),
        ("remove", "tap", "push"),
        (Parameter("force", (0.0,), (10.0,), (3,), users, "pos"),),
    )
    g = torch.Generator().manual_seed(seed)
    a = torch.randint(0, 3, (n,), generator=g)
    vis0 = torch.randint(0, 2, (n,), generator=g)
    force = torch.rand(n, 1, generator=g, dtype=DTYPE) * 10
    uses = net.mixture("force").uses[a]
    force[~uses] = float("nan")
    f = force.nan_to_num()
    falls = torch.rand(n, generator=g, dtype=DTYPE) < f[:, 0] / 12
    vis1 = torch.where((a == 0) | falls, 0, vis0)
    pos = torch.where(a[:, None] == 1, torch.sqrt(f), torch.where(a[:, None] == 2, 0.3 * f, 0.0))
    pos = pos + 0.1 * torch.randn(n, 1, generator=g, dtype=DTYPE)
    rows = net.encode_indices(
        {
            "initial.visible": vis0,
            "action": a,
            "param.force": force,
            "end.visible": vis1,
            "end.pos": pos,
        }
    )
    masks = {
        "action": torch.rand(n, generator=g) > 0.3,
        "initial.visible": torch.rand(n, generator=g) > 0.2,
    }
    return net, rows, masks


# sparse networks with closed-form answers, for elimination
def sparse_network(k: int) -> EffectNetwork:
    """``k`` binary features; each end feature's parents: its own initial value and the
    action."""
    return EffectNetwork(
        tuple(Discrete(f"f{i}", (0, 1)) for i in range(k)),
        ("push", "lift", "wait"),
        parents={f"end.f{i}": (f"initial.f{i}", "action") for i in range(k)},
    )


def closed_form(params, k: int, y: torch.Tensor, observed: int):
    """With the initial state latent and ends ``0..observed-1`` observed (``y`` ``(n,
    observed)``), the posterior factorises given the action: per row, p(a | y), the
    unseen mass per action, each unobserved end feature's marginal, and the targets'
    unseen mass."""
    log_a = params["action"].probs.log().expand(y.shape[0], -1).clone()
    all_seen = torch.ones_like(log_a)
    for i in range(observed):
        prior = params[f"initial.f{i}"].probs  # (2,)
        table = params[f"end.f{i}"].probs  # (x, a, y)
        seen = params[f"end.f{i}"].n > 0  # (x, a)
        like = prior[:, None, None] * table[:, :, :]  # (x, a, y)
        joint = like[:, :, y[:, i]].permute(2, 0, 1)  # (n, x, a)
        log_a = log_a + joint.sum(1).log()
        all_seen = all_seen * (joint * seen).sum(1) / joint.sum(1)
    post = (log_a - log_a.logsumexp(-1, keepdim=True)).exp()
    marginals, seen_targets = {}, torch.ones(3, dtype=DTYPE)
    for j in range(observed, k):
        prior, table = params[f"initial.f{j}"].probs, params[f"end.f{j}"].probs
        per_action = (prior[:, None, None] * table).sum(0)  # (a, y)
        marginals[f"f{j}"] = post @ per_action
        seen_targets = seen_targets * (prior[:, None] * (params[f"end.f{j}"].n > 0)).sum(0)
    return post, 1 - all_seen, marginals, post @ (1 - seen_targets)


# the door world: a door, a drawer and a switch
DOOR_ACTIONS = ("press", "pull", "turn", "wait")


DOOR_STATES = {
    "door": ("locked", "shut", "open"),
    "drawer": ("shut", "open"),
    "switch": ("off", "on"),
}


#: the door's end state follows its start, the action and the handle; the others their own
DOOR_PARENTS = {
    "end.door": ("initial.door", "action", "initial.handle_angle"),
    "end.drawer": ("initial.drawer", "action"),
    "end.switch": ("initial.switch", "action"),
    "end.handle_angle": ("initial.handle_angle", "action"),
}


def door_world(parents=DOOR_PARENTS, *, handle=True) -> EffectNetwork:
    """The network; ``parents=None``: the paper's default (every initial feature and the
    action behind every end feature); ``handle=False``: the purely discrete version."""
    features = tuple(Discrete(name, states) for name, states in DOOR_STATES.items())
    if handle:
        features += (Continuous("handle_angle", 1),)
    return EffectNetwork(features=features, actions=DOOR_ACTIONS, parents=parents or {})


def door_rows(n: int, seed: int = 0, *, handle: bool = True) -> dict[str, np.ndarray]:
    """Training rows by site, labels for discrete sites, ``(n, 1)`` radians for the angle."""
    rng = np.random.default_rng(seed)
    action = rng.choice(DOOR_ACTIONS, n)
    door = rng.choice(DOOR_STATES["door"], n, p=[0.3, 0.4, 0.3])
    drawer = rng.choice(DOOR_STATES["drawer"], n)
    switch = rng.choice(DOOR_STATES["switch"], n)
    angle = rng.uniform(-1.0, 1.0, n)
    turned = action == "turn"
    # the door: a softmax of the angle; turning the handle far enough opens it
    logits = np.stack(
        [
            np.where(door == "locked", 3.0 - 3.0 * turned * angle, -1.0),
            np.where(action == "pull", 1.0, 0.0),
            np.where(turned, 4.0 * angle, -2.0),
        ],
        1,
    )
    if not handle:
        logits[:, 2] = np.where(turned, 1.5, -2.0)
    prob = np.exp(logits - logits.max(1, keepdims=True))
    prob /= prob.sum(1, keepdims=True)
    end_door = (rng.random(n)[:, None] > prob.cumsum(1)).sum(1).clip(0, 2)
    flipped = (action == "press") & (rng.random(n) < 0.9)
    stuck = rng.random(n) < 0.1
    rows = {
        "initial.door": door,
        "initial.drawer": drawer,
        "initial.switch": switch,
        "action": action,
        "end.door": np.array(DOOR_STATES["door"])[end_door],
        "end.drawer": np.where((action == "pull") & ~stuck, "open", drawer),
        "end.switch": np.where(flipped, np.where(switch == "on", "off", "on"), switch),
    }
    if handle:
        rows["initial.handle_angle"] = angle[:, None]
        end = np.where(turned, 0.5 * angle + 0.3, angle) + rng.normal(0.0, 0.05, n)
        rows["end.handle_angle"] = end[:, None]
    return rows


# ------------------------------------------------------ small discrete networks (pgmpy)
LABELS = {
    "str": lambda k: ("lo", "mid", "hi")[:k],
    "int": lambda k: (7, -1, 2)[:k],
    "bool": lambda k: (False, True),
}


@st.composite
def discrete_networks(draw):
    """Small discrete networks with str, int and bool labels, some end-only features."""
    features = []
    for i in range(draw(st.integers(1, 3))):
        labels = draw(st.sampled_from(sorted(LABELS)))
        k = 2 if labels == "bool" else draw(st.integers(2, 3))
        initial = i == 0 or draw(st.booleans())
        features.append(Discrete(f"f{i}", LABELS[labels](k), initial=initial))
    actions = ("push", "pull", "wait")[: draw(st.integers(2, 3))]
    return EffectNetwork(tuple(features), actions)


@st.composite
def declared_networks(draw):
    """Small discrete networks with declared parent sets: initial sites on earlier
    initial sites, end sites on any initial sites, the action and earlier end sites."""
    base = draw(discrete_networks())
    features = base.features
    initial = [f"initial.{f.name}" for f in features if f.initial]
    ends = [f"end.{f.name}" for f in features]
    parents = {}
    for i, site in enumerate(initial):
        parents[site] = tuple(q for q in initial[:i] if draw(st.booleans()))
    for i, site in enumerate(ends):
        pool = [*initial, "action", *ends[:i]]
        parents[site] = tuple(q for q in pool if draw(st.booleans()))
    return EffectNetwork(features, base.actions, parents=parents)


def pgmpy_marginal(ve, site, evidence):
    """p(site | evidence) from pgmpy, in the order of the factor's state names."""
    factor = ve.query([site], evidence=evidence, show_progress=False)
    return factor.state_names[site], torch.as_tensor(factor.values, dtype=DTYPE)


def counts_of(params):
    return {site: cpd.n for site, cpd in params.cpds.items()}


def drawn_demonstrations(
    net: EffectNetwork, g: np.random.Generator, data, n: int = 2, times: int = 3
):
    """Demonstrations of ``net`` with values and labels hidden at random, and their labels.

    Per time, each feature the time can show (an initial feature at every time, an end-only
    one after the first): a discrete one shown at a random state or hidden; a continuous one
    shown at a random value, hidden only where it is an end-only outcome. Each step's label is
    an action index or None. ``g`` draws the values, ``data`` (hypothesis) what is hidden.
    """
    demos, labels = [], []
    for _ in range(n):
        demo = []
        for t in range(times):
            state = {}
            for f in net.features:
                if not (f.initial or t):
                    continue
                if isinstance(f, Continuous):
                    hide = not f.initial and data.draw(st.booleans())
                    state[f.name] = None if hide else [float(g.normal(0.0, 2.0))]
                else:
                    hide = data.draw(st.booleans())
                    state[f.name] = None if hide else f.states[g.integers(f.cardinality)]
            demo.append(state)
        demos.append(demo)
        labels.append(
            [data.draw(st.sampled_from([None, *range(len(net.actions))])) for _ in demo[1:]]
        )
    return demos, labels

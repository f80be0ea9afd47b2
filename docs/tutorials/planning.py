# %% [markdown]
# # Planning on a door world
#
# A fitted network says what one action does; chained, the end of one step being the
# start of the next, it says which actions reach a goal and how likely they are to. This
# tutorial fits a door world from logged trials, reads its transitions
# ({func}`inference.transitions`), plans to open the door ({func}`inference.plan`) and
# draws the plan with {func}`inference.plots.plot_plan`: the policy (the action each
# state takes with so many actions left) and the most likely path to the goal. The page
# [Planning with a network](../planning.md) explains each piece.
#
# This page is a script, {download}`planning.py <planning.py>`, run when the site is
# built: `python docs/tutorials/planning.py` runs it (a window shows the figure). The
# site runs it small (`EFFECT_NETWORKS_TUTORIALS=tiny`: fewer logged trials).

# %%
import os

import matplotlib.pyplot as plt
import numpy as np
from effect_networks.experiments.switch_worlds import switch_world
from effect_networks.inference import fit, plan, transitions
from effect_networks.inference.plots import plot_plan
from effect_networks.models import Discrete, EffectNetwork

TINY = os.environ.get("EFFECT_NETWORKS_TUTORIALS") == "tiny"
TRIALS = 600 if TINY else 5000  # logged trials

# %% [markdown]
# A door is closed or open, locked or unlocked. In the world the trials come from,
# `unlock` unlocks it 9 times in 10, `push` opens a closed, unlocked door 4 times in 5
# (a locked one never), and `wait` changes nothing. The network knows none of this: it
# has the two features and the three actions, and learns the rest from the trials.

# %%
net = EffectNetwork(
    features=(Discrete("door", ("closed", "open")), Discrete("lock", ("locked", "unlocked"))),
    actions=("unlock", "push", "wait"),
)

rng = np.random.default_rng(0)
door = rng.choice(["closed", "open"], TRIALS)
lock = rng.choice(["locked", "unlocked"], TRIALS)
action = rng.choice(net.actions, TRIALS)
unlocks = (action == "unlock") & (rng.random(TRIALS) < 0.9)
opens = (action == "push") & (door == "closed") & (lock == "unlocked")
opens &= rng.random(TRIALS) < 0.8
trials = {
    "initial.door": door,
    "initial.lock": lock,
    "action": action,
    "end.door": np.where(opens, "open", door),
    "end.lock": np.where(unlocks, "unlocked", lock),
}
params = fit(net, trials).params

# %% [markdown]
# The transitions: for every state and action, the next state's distribution, read
# exactly from the fitted tables. Pushing a closed, unlocked door opens it about 4 times
# in 5.

# %%
steps = transitions(net, params)
print(steps.space.states)
after_push = steps.next_states(("closed", "unlocked"), "push")
print({state: round(p, 3) for state, p in after_push.items()})

# %% [markdown]
# The plan: from a closed, locked door, open it within three actions. With three
# actions left the door is unlocked, then pushed, with one action to spare to repeat the
# one that failed; the success probability sums every way that can go.

# %%
route = plan(net, params, ("closed", "locked"), {"door": "open"}, horizon=3)
print(f"success within 3 actions: {route.success:.3f}")
print("first action:", route.action(("closed", "locked")))
print("most likely path:", route.path, f"(p = {route.path_probability:.3f})")

# %% [markdown]
# The policy as a grid, each cell the action taken in a state with so many actions left
# and the probability of reaching the goal from there (with one action left a locked
# door cannot be opened: its chance is 0, whichever action it takes); and the most
# likely path, one marker per state.

# %%
fig, (left, right) = plt.subplots(1, 2, figsize=(12, 4), width_ratios=(3, 2))
plot_plan(route, ax=left)
plot_plan(route, ax=right, show="path")
fig.tight_layout()
plt.show()

# %% [markdown]
# ## A world of many features
#
# Sixty-four switches, one `flip` action each and `wait`: `2^64` states, a dense table
# out of any reach. The goal reads three switches; their next values read only their
# own and their neighbours' (declared with `parents=`), so the plan is made over those
# four switches, factor by factor, with the answer the dense planner would give.

# %%
world = switch_world(64, "sparse")
big = plan(world.net, world.params, world.start, world.goal, horizon=6)
print(big.route, big.features, f"success {big.success:.4f}, unseen {big.unseen:.2f}")
print("first action:", big.action(world.start))

# %% [markdown]
# A coupled world, where each switch's next value reads the next switch and every
# action disturbs three others, leaves little to project away: the goal on eight
# switches reads all of them. Past `budget=` joint states the plan is approximate: it is
# made on the goal's switches and their nearest neighbours, then played 40,000 times in
# the full model, and its success is a lower bound that holds with 95 % confidence.

# %%
coupled = switch_world(12 if TINY else 24, "coupled")
rough = plan(coupled.net, coupled.params, coupled.start, coupled.goal, 10, budget=1 << 10)
c = rough.certificate
print(rough.route, f"on {len(rough.features)} features: success >= {c.lower:.3f}")
print(f"(estimate {c.estimate:.3f} from {c.episodes} runs, seed {c.seed})")

fig, ax = plt.subplots(figsize=(8, 3))
plot_plan(big, ax=ax, show="path")
fig.tight_layout()
plt.show()

# %% [markdown]
# # Reading a demonstration
#
# A demonstration is what a robot sees while someone shows it a task: the scene after
# each action, not the actions themselves. {func}`inference.explain` reads it back with a
# fitted network: the posterior over each step's action, the most probable sequence, and
# a flag on any step the network cannot explain. {func}`inference.plots.plot_demonstration`
# draws the answer. The page [Demonstrations read as actions](../demonstrations.md)
# explains the model behind it.
#
# This page is a script, {download}`demonstration.py <demonstration.py>`, run when the
# site is built: `python docs/tutorials/demonstration.py` runs it (a window shows the
# figure). The site runs it small (`EFFECT_NETWORKS_TUTORIALS=tiny`: fewer training rows
# and drawn demonstrations).

# %%
import os

import matplotlib.pyplot as plt
import numpy as np
from effect_networks.inference import explain, fit
from effect_networks.inference.plots import plot_demonstration
from effect_networks.inference.sequences.demonstration import simulate_demonstrations
from effect_networks.models import Continuous, Discrete, EffectNetwork, Parameter

TINY = os.environ.get("EFFECT_NETWORKS_TUTORIALS") == "tiny"
ROWS = 500 if TINY else 2000  # training rows
DEMOS = 20 if TINY else 200  # demonstrations drawn from the fitted model

# %% [markdown]
# The paper's Fig. 1 network: a can, visible or not, at a position; `look` changes
# nothing, `remove` takes the can away, `tap` pushes it with a force, the harder the
# further. It is fitted on trials of all three actions, as in the README's quick start.

# %%
net = EffectNetwork(
    features=(Discrete("visible", (False, True)), Continuous("position", 1)),
    actions=("look", "remove", "tap"),
    parameters=(
        Parameter("force", low=0.0, high=20.0, bins=8, actions=("tap",), affects="position"),
    ),
)
rng = np.random.default_rng(0)
action = rng.choice(net.actions, ROWS)
visible = rng.random(ROWS) < 0.7
position = rng.uniform(-1.0, 1.0, (ROWS, 1))
force = np.where(action[:, None] == "tap", rng.uniform(0.0, 20.0, (ROWS, 1)), np.nan)
rolled = 0.02 * np.nan_to_num(force) + 0.0015 * np.nan_to_num(force) ** 2  # metres
params = fit(
    net,
    {
        "initial.visible": visible,
        "initial.position": position,
        "action": action,
        "param.force": force,
        "end.visible": visible & (action != "remove"),
        "end.position": position + rolled + rng.normal(0.0, 0.01, (ROWS, 1)),
    },
).params

# %% [markdown]
# One demonstration, four scenes: the can sits at 0, moves about 0.35 m, stays where it
# is, then is gone. The third scene does not say whether the can is visible (`None`):
# that state is latent and carries over to the next step.

# %%
demo = [
    {"visible": True, "position": [0.0]},
    {"visible": True, "position": [0.35]},
    {"visible": None, "position": [0.35]},
    {"visible": False, "position": [0.35]},
]
story = explain(net, params, demo)
print("most probable actions:", story.best_names[0])
print("P(tap) per step:", np.round(story.prob("tap")[0].numpy(), 3))
print("steps the network cannot explain:", story.implausible[0].tolist())

# %% [markdown]
# Demonstrations drawn from the fitted model itself, with the actions that drew them:
# how often does `explain` read the drawn action back? Not always: once the can is gone,
# `look` and `remove` look alike, and so do `look` and a `tap` of almost no force.

# %%
states, drawn = simulate_demonstrations(net, params, DEMOS, 3, seed=1)
read = explain(net, params, states)
share = (np.array(read.best_names) == drawn).mean()
print(f"actions read back: {share:.0%} of {drawn.size}")

# %% [markdown]
# The demonstration above as a heat map: one column per step, one row per action, the
# shade the action's posterior probability, a dot on each step's action in the most
# probable sequence; beside it the first drawn demonstration with a tap in it, its drawn
# actions in the title.

# %%
tapped = np.flatnonzero((drawn == "tap").any(axis=1))
row = int(tapped[0]) if tapped.size else 0
fig, (left, right) = plt.subplots(1, 2, figsize=(12, 4))
plot_demonstration(story, ax=left)
left.set_title("the demonstration above")
plot_demonstration(read, ax=right, row=row)
right.set_title(f"drawn demonstration {row}: {', '.join(drawn[row])}")
fig.tight_layout()
plt.show()

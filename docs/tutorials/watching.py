# %% [markdown]
# # Learning from watching
#
# A person opens cupboards and switches lights while the robot watches: it sees the
# scene change, not the names of the actions. {func}`inference.fit_demonstrations`
# learns the effect network from such demonstrations, a few of whose steps are labelled,
# by EM over the unknown actions. The learned network then plans and reads new
# demonstrations back, as one fitted on labelled trials does. The page
# [Demonstrations read as actions](../demonstrations.md) says what the fit assumes.
#
# This page is a script, {download}`watching.py <watching.py>`, run when the site is
# built: `python docs/tutorials/watching.py` runs it (a window shows the figures). The
# site runs it a little smaller (`EFFECT_NETWORKS_TUTORIALS=tiny`: fewer demonstrations).

# %%
import os

import matplotlib.pyplot as plt
import numpy as np
from effect_networks.experiments.switch_worlds import switch_world
from effect_networks.inference import explain, fit_demonstrations, plan
from effect_networks.inference.plots import plot_table
from effect_networks.inference.sequences.demonstration import simulate_demonstrations

TINY = os.environ.get("EFFECT_NETWORKS_TUTORIALS") == "tiny"
DEMOS = 150 if TINY else 200  # demonstrations of 5 steps

# %% [markdown]
# The world: six switches (a kitchen's cupboards and lights), one `flip` action each and
# `wait`. A flip works 9 times in 10, and a switch whose neighbour is on flips by itself
# 1 time in 20. Its true tables draw the demonstrations; a tenth of their steps are
# labelled.

# %%
world = switch_world(6, "sparse")
states, actions = simulate_demonstrations(world.net, world.params, DEMOS, 5, seed=1)
labelled = np.random.default_rng(0).random(actions.shape) < 0.1
labels = np.where(labelled, actions, None)
print(f"{DEMOS} demonstrations, {int(labelled.sum())} of {actions.size} steps labelled")

# %% [markdown]
# The fit: EM over the unlabelled steps' actions, started from the labelled steps, from
# the steps grouped by the change they cause, and from random tables; the best start is
# kept. The result says how well the learned network recognises the labelled steps with
# their labels hidden.

# %%
watched = fit_demonstrations(world.net, states, labels)
print(f"{len(watched.log_likelihoods) - 1} EM steps, log-likelihood never falling")
print(f"recognises {100 * watched.agreement:.0f} % of the labelled steps")

# %% [markdown]
# What `flip_0` does to switch 0, learned beside true: the table of `end.f0` given its
# start, the action and its neighbour.

# %%
fig, (left, right) = plt.subplots(1, 2, figsize=(12, 4))
plot_table(world.net, watched.params, "end.f0", ax=left)
left.set_title("learned from watching")
plot_table(world.net, world.params, "end.f0", ax=right)
right.set_title("true")
fig.tight_layout()
plt.show()

# %% [markdown]
# The learned network plans (three switches on, within five actions) and reads a new
# demonstration back as actions. A flip that failed (1 time in 10) changes nothing: it
# reads as `wait`, as it would to anyone who only saw the states.

# %%
route = plan(world.net, watched.params, world.start, world.goal, horizon=5)
print(f"plan: first {route.action(world.start)}, success {route.success:.3f}")
new, truth = simulate_demonstrations(world.net, world.params, 1, 4, seed=7)
story = explain(world.net, watched.params, new)
print("read back:", story.best_names[0], "| done:", tuple(truth[0]))

# %% [markdown]
# # Pictures of a fitted network
#
# Declare a small network, draw training rows from a known model
# ({func}`inference.simulate`), fit the network on them, and draw what was fitted with
# {mod}`inference.plots`: the graph, a table, the parameter's clusters over the rows, and
# the posterior over actions for one observed change. Every plot function draws into an
# axes it is given (or a new figure) and returns it, so the four pictures share one
# figure here.
#
# This page is a script, {download}`plots.py <plots.py>`, run when the site is built:
# `python docs/tutorials/plots.py` runs it (a window shows the figure), an editor runs it
# cell by cell. The site runs it small (`EFFECT_NETWORKS_TUTORIALS=tiny`: fewer training
# rows), so its numbers are rougher than a full run's.

# %%
import os

import matplotlib.pyplot as plt
from effect_networks.inference import fit, infer_action, simulate
from effect_networks.inference.plots import (
    plot_action_posterior,
    plot_clusters,
    plot_network,
    plot_table,
)
from effect_networks.models import Continuous, Discrete, EffectNetwork, Parameter, random_params

TINY = os.environ.get("EFFECT_NETWORKS_TUTORIALS") == "tiny"
ROWS = 400 if TINY else 2000  # training rows

# %% [markdown]
# A can that is visible or not; `tap` pushes it with a force whose range is cut into
# four clusters, and it moves by some displacement. Whether the can stays visible
# depends on whether it was and on the action, so that site is a table; the
# displacement depends on the action (and the force) only.

# %%
net = EffectNetwork(
    features=(Discrete("visible", (False, True)), Continuous("displacement", 1, initial=False)),
    actions=("look", "remove", "tap"),
    parameters=(
        Parameter("force", low=0.0, high=20.0, bins=4, actions=("tap",), affects="displacement"),
    ),
    parents={"end.visible": ("initial.visible", "action"), "end.displacement": ("action",)},
)

# %% [markdown]
# Rows drawn from a known (random) model, and the network fitted on them.

# %%
truth = random_params(net, seed=3)
rows = simulate(net, truth, ROWS, seed=2)
params = fit(net, rows).params

# %% [markdown]
# One observed change: the can was visible, is still visible and moved by 0.5. Which
# action was it?

# %%
posterior = infer_action(
    net,
    params,
    {"initial.visible": True, "end.visible": True, "end.displacement": [0.5]},
)
print(dict(zip(posterior.actions, posterior.probs[0].tolist(), strict=True)))

# %% [markdown]
# The four pictures. The clusters are drawn over the force and the displacement: one
# joint Gaussian per cluster (1 and 2 standard deviations), over the training rows of
# `tap`.

# %%
fig, axes = plt.subplots(2, 2, figsize=(12, 9))
plot_network(net, ax=axes[0, 0])
plot_table(net, params, "end.visible", ax=axes[0, 1])
plot_clusters(net, params, "force", rows, ax=axes[1, 0], feature="displacement")
plot_action_posterior(posterior, ax=axes[1, 1])
fig.tight_layout()
plt.show()

# %% [markdown]
# # Your own data
#
# Logged trials come as they come: a table with one column per site, and gaps where
# nobody wrote a label down or a sensor lost the object. This tutorial takes such a
# table (a pandas `DataFrame`), fits a network on it by EM ({func}`inference.fit`
# fills the gaps), scores it ({func}`inference.bic`, {func}`inference.cross_validate`)
# and lets {func}`inference.learn_structure` choose each end feature's parents. The pages
# [Data frames](../frames.md), [Missing values](../missing.md),
# [Scores and model selection](../scores.md) and [Structure learning](../structure.md)
# explain each step.
#
# This page is a script, {download}`own_data.py <own_data.py>`, run when the site is
# built: `python docs/tutorials/own_data.py` runs it (a window shows the figure). It
# needs pandas, the `data` extra. The site runs it small
# (`EFFECT_NETWORKS_TUTORIALS=tiny`: fewer trials).

# %%
import os

import matplotlib.pyplot as plt
import numpy as np
from effect_networks.inference import bic, cross_validate, fit, learn_structure
from effect_networks.inference.plots import plot_network
from effect_networks.models import Continuous, Discrete, EffectNetwork, Parameter, to_frame

TINY = os.environ.get("EFFECT_NETWORKS_TUTORIALS") == "tiny"
TRIALS = 400 if TINY else 2000

# %% [markdown]
# The trials: a can, visible or not, at a position; `look`, `remove` or `tap` with a
# force. In the world they come from, whether the can stays visible depends on whether
# it was and on the action only, not on where it is. They are drawn here, and put in the
# table a CSV file of them would give ({func}`models.to_frame`): one column per site
# (a vector's columns would be `end.position[0]`, `end.position[1]`, ...).

# %%
declared = EffectNetwork(  # the paper's Fig. 1: every end feature depends on everything
    features=(Discrete("visible", (False, True)), Continuous("position", 1)),
    actions=("look", "remove", "tap"),
    parameters=(
        Parameter("force", low=0.0, high=20.0, bins=8, actions=("tap",), affects="position"),
    ),
)
rng = np.random.default_rng(0)
action = rng.choice(declared.actions, TRIALS)
visible = rng.random(TRIALS) < 0.7
position = rng.uniform(-1.0, 1.0, (TRIALS, 1))
force = np.where(action[:, None] == "tap", rng.uniform(0.0, 20.0, (TRIALS, 1)), np.nan)
rolled = 0.02 * np.nan_to_num(force) + 0.0015 * np.nan_to_num(force) ** 2  # metres
data = {
    "initial.visible": visible,
    "initial.position": position,
    "action": action,
    "param.force": force,
    "end.visible": visible & (action != "remove"),
    "end.position": position + rolled + rng.normal(0.0, 0.01, (TRIALS, 1)),
}
trials = to_frame(declared, data).astype({"end.visible": object})
trials.loc[::10, "end.visible"] = None  # labels nobody wrote down
trials.loc[5::10, "end.position"] = np.nan  # an occluded measurement
print(trials.head(6).round(3).to_string())

# %% [markdown]
# Fitted on the table as it is: the gaps make it EM, which fills each gap with its
# expectation under the current fit and refits, the log-likelihood of the rows as they
# were observed rising at every iteration. BIC scores the fit on the same rows, the gaps
# summed out exactly.

# %%
fitted = fit(declared, trials)
print(f"EM: {len(fitted.log_likelihoods)} iterations")
print(f"BIC of the declared network: {bic(declared, fitted.params, trials):.1f}")

# %% [markdown]
# Which parents does each end feature need? `learn_structure` searches the parents that
# the declaration allows for the best BIC (here on the complete rows), and the learned
# network is compared with the declared one held out, by 5-fold cross-validation (the
# mean held-out log-likelihood per row, higher is better).

# %%
learned = learn_structure(data, declared.features, declared.actions, declared.parameters)
print("end.visible's parents:", dict(learned.parents)["end.visible"])
held_out = {"declared": cross_validate(declared, data), "learned": cross_validate(learned, data)}
for name, result in held_out.items():
    print(f"{name}: {result.mean:.3f} per row held out")

# %% [markdown]
# EM's log-likelihood by iteration, and the learned network's graph: `end.visible` no
# longer listens to the position.

# %%
fig, (left, right) = plt.subplots(1, 2, figsize=(12, 4.5), width_ratios=(2, 3))
left.plot(np.arange(1, len(fitted.log_likelihoods) + 1), fitted.log_likelihoods, "o-")
left.set_xlabel("EM iteration")
left.set_ylabel("log-likelihood of the observed values")
plot_network(learned, ax=right)
right.set_title("the learned network")
fig.tight_layout()
plt.show()

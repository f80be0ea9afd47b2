# %% [markdown]
# # Rows through a CSV file
#
# Logged trials usually arrive as a table. Here rows are drawn from a known model
# ({func}`inference.simulate`, straight into a pandas `DataFrame` with
# `as_frame=True`), written to a CSV file, read back with pandas, and the network is
# fitted on the frame as it was read. A few trials whose action was not logged are then
# asked for it, and the answer is a frame too: one probability column per action, labels
# rather than indices. The column convention is on the page [Data frames](../frames.md).
#
# This page is a script, {download}`csv_round_trip.py <csv_round_trip.py>`, run when the
# site is built: `python docs/tutorials/csv_round_trip.py --out rows.csv` (`--rows` sets
# the training rows; the file goes to a temporary folder by default). It needs pandas,
# the `data` extra. The site runs it small (`EFFECT_NETWORKS_TUTORIALS=tiny`).

# %%
import argparse
import os
import tempfile
from pathlib import Path

import matplotlib.pyplot as plt
import pandas as pd
from effect_networks.inference import fit, infer_action, simulate
from effect_networks.inference.plots import plot_action_posterior
from effect_networks.models import Continuous, Discrete, EffectNetwork, Parameter, random_params

parser = argparse.ArgumentParser(description="Rows through a CSV file.")
parser.add_argument("--out", type=Path, default=Path(tempfile.mkdtemp()) / "rows.csv")
tiny = os.environ.get("EFFECT_NETWORKS_TUTORIALS") == "tiny"
parser.add_argument("--rows", type=int, default=300 if tiny else 2000)
args, _ = parser.parse_known_args()  # a notebook kernel's own arguments are left alone

# %% [markdown]
# A can that is visible or not, lying at a 2-d position; `tap` pushes it with a force
# and it moves by some displacement. The position is a vector: its columns are
# `initial.position[0]`, `initial.position[1]`, and likewise for its end state.

# %%
net = EffectNetwork(
    features=(
        Discrete("visible", (False, True)),
        Continuous("position", 2),
        Continuous("displacement", 1, initial=False),
    ),
    actions=("look", "remove", "tap"),
    parameters=(
        Parameter("force", low=0.0, high=20.0, bins=4, actions=("tap",), affects="displacement"),
    ),
)

# %% [markdown]
# Rows from a known (random) model, written as CSV and read back. The force is empty
# in the rows whose action is not `tap` (NaN: that action does not use it).

# %%
truth = random_params(net, seed=3)
simulate(net, truth, args.rows, seed=2, as_frame=True).to_csv(args.out, index=False)
rows = pd.read_csv(args.out)
print(rows.head(3).to_string())

# %% [markdown]
# The network fitted on the frame as read: `True`/`False` came back as bools, the action
# names as strings, each matched to the declared states.

# %%
params = fit(net, rows).params

# %% [markdown]
# Three trials without their action (and without the force): which action was it?

# %%
trials = rows.drop(columns=["action", "param.force", "cluster.force"]).head(3)
posterior = infer_action(net, params, trials)
print(posterior.to_frame(index=trials.index).round(3).to_string())

# %% [markdown]
# The first of them drawn: the posterior over its action, the most probable one darker.

# %%
ax = plot_action_posterior(posterior, row=0)
ax.set_title(f"trial {trials.index[0]}: which action?")
plt.show()

"""The user guide's shared set-up: README's quick start, built once for any guide page.

A guide page's first snippet imports from here what it uses of the quick start: the
network ``net``, its training rows ``data``, the fitted ``params``, the evidence ``ev``
(the object visible at 0 m) and ``aim``, the parameter posterior of the force that
rolls it to 0.35 m. The code is the quick start's (``tests/test_readme.py`` checks that
both build the same); run a page's snippets from this folder, or with it on the path.
"""

import numpy as np

from effect_networks import Continuous, Discrete, EffectNetwork, Parameter, fit, infer_parameter

net = EffectNetwork(
    features=(Discrete("visible", (False, True)), Continuous("position", 1)),
    actions=("look", "remove", "tap"),
    parameters=(
        Parameter("force", low=0.0, high=20.0, bins=8, actions=("tap",), affects="position"),
    ),
)

# Training rows by site: initial.<feature>, action, param.<parameter>, end.<feature>.
rng = np.random.default_rng(0)
n = 2000
action = rng.choice(net.actions, n)
visible = rng.random(n) < 0.7
position = rng.uniform(-1.0, 1.0, (n, 1))
force = np.where(action[:, None] == "tap", rng.uniform(0.0, 20.0, (n, 1)), np.nan)
rolled = 0.02 * np.nan_to_num(force) + 0.0015 * np.nan_to_num(force) ** 2  # metres
data = {
    "initial.visible": visible,
    "initial.position": position,
    "action": action,
    "param.force": force,
    "end.visible": visible & (action != "remove"),
    "end.position": position + rolled + rng.normal(0.0, 0.01, (n, 1)),
}
params = fit(net, data).params

ev = {"initial.visible": [True], "initial.position": [[0.0]]}
aim = infer_parameter(net, params, "force", ev | {"action": ["tap"], "end.position": [[0.35]]})

__all__ = ["aim", "data", "ev", "net", "params"]

"""The softmax kind's Newton fit against its optimality conditions, written out in numpy."""

import numpy as np
import torch
from effect_networks.models.cpds import SoftmaxCPD
from effect_networks.models.declaration import DTYPE
from hypothesis import given, settings
from hypothesis import strategies as st


def numpy_gradient(weight, bias, index, x, y, w, l2):
    """The gradient of sum_i w_i -log softmax(W[g_i] x_i + b[g_i])[y_i] + l2/2 |W|^2,
    per configuration: ``(G, K, p)`` and ``(G, K)``."""
    logits = np.einsum("nkp,np->nk", weight[index], x) + bias[index]
    logits -= logits.max(1, keepdims=True)
    prob = np.exp(logits)
    prob /= prob.sum(1, keepdims=True)
    residual = w[:, None] * (prob - np.eye(weight.shape[1])[y])
    grad_w = l2 * weight.copy()
    grad_b = np.zeros_like(bias)
    np.add.at(grad_w, index, residual[:, :, None] * x[:, None, :])
    np.add.at(grad_b, index, residual)
    return grad_w, grad_b


@settings(max_examples=40, deadline=None)
@given(
    n=st.integers(1, 80),
    k=st.integers(1, 4),
    p=st.integers(1, 3),
    groups=st.integers(1, 3),
    l2=st.sampled_from([1e-3, 0.01, 1.0]),
    magnitude=st.sampled_from([1e-6, 1.0, 1e3, 1e60, 1e140]),
    weighted=st.booleans(),
    seed=st.integers(0, 2**16),
)
def test_newton_meets_the_optimality_conditions(n, k, p, groups, l2, magnitude, weighted, seed):
    rng = np.random.default_rng(seed)
    x = rng.normal(size=(n, p)) * magnitude
    index = rng.integers(0, groups, n)
    y = rng.integers(0, k, n)
    w = rng.uniform(0.0, 2.0, n) if weighted else np.ones(n)
    cpd = SoftmaxCPD("end.s", ("a",), (groups,), k, ("initial.x",), p)
    start = cpd.initialize()
    found = cpd.maximise(
        torch.as_tensor(index),
        torch.as_tensor(x),
        torch.as_tensor(y),
        start,
        weights=torch.as_tensor(w) if weighted else None,
        l2=l2,
    )
    assert found.converged
    weight, bias = found.params.weight.numpy(), found.params.bias.numpy()
    assert np.isfinite(weight).all() and np.isfinite(bias).all()
    grad_w, grad_b = numpy_gradient(weight, bias, index, x, y, w, l2)
    # each configuration's gradient against its summed row scale
    scale = np.zeros(groups)
    np.add.at(scale, index, w * np.maximum(1.0, np.abs(x).max(1)))
    scale = np.maximum(scale, 1.0)
    assert (np.abs(grad_w).max((1, 2)) <= 1e-8 * scale).all()
    assert (np.abs(grad_b).max(1) <= 1e-8 * scale).all()
    # Newton with a line search only descends, and the offsets keep their sum
    assert all(
        b <= a + 1e-9 * abs(a) for a, b in zip(found.objectives, found.objectives[1:], strict=False)
    )
    torch.testing.assert_close(found.params.bias.sum(-1), start.bias.sum(-1), atol=1e-9, rtol=0)
    assert found.params.weight.dtype == DTYPE

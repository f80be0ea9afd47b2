"""What the per-question suites share: one comparison of two answers field by field,
and a spy on the traced function that :func:`inference.compile`'s methods fall back to."""

from __future__ import annotations

import dataclasses

import effect_networks.inference.compiled as surface
import torch

#: Compiled and traced answers agree to this (absolute and relative), every field.
TOLERANCE = 1e-12


def assert_same_answer(a, b, path: str = "answer") -> None:
    """Every field of the results ``a`` and ``b`` equal: tensors to :data:`TOLERANCE`
    (bool and integer ones exactly), nested results, mixtures and dicts field by field."""
    assert type(a) is type(b), (path, type(a), type(b))
    if isinstance(a, torch.Tensor):
        assert a.shape == b.shape and a.dtype == b.dtype, (path, a.shape, b.shape)
        if a.is_floating_point():
            torch.testing.assert_close(a, b, atol=TOLERANCE, rtol=TOLERANCE, msg=path)
        else:
            assert torch.equal(a, b), path
    elif dataclasses.is_dataclass(a):
        for f in dataclasses.fields(a):
            assert_same_answer(getattr(a, f.name), getattr(b, f.name), f"{path}.{f.name}")
    elif isinstance(a, dict):
        assert a.keys() == b.keys(), (path, a.keys(), b.keys())
        for k in a:
            assert_same_answer(a[k], b[k], f"{path}[{k!r}]")
    else:
        assert a == b, (path, a, b)


class TracedCalls:
    """Counts the calls the compiled surface makes to the traced ``name``
    (``monkeypatch`` replaces the surface's reference with a counting wrapper)."""

    def __init__(self, monkeypatch, name: str):
        self.calls = 0
        traced = getattr(surface, name)

        def counting(*args, **kwargs):
            self.calls += 1
            return traced(*args, **kwargs)

        monkeypatch.setattr(surface, name, counting)

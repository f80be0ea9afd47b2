"""experiments.can_demonstration: a hand-made can world read back field by field (a
hidden configuration resolved by the throw after it), the thrown demonstrations keep
to the network's configurations, the whole experiment at the tiny scale, its settings."""

import numpy as np
import pytest
import torch
from effect_networks.experiments import can_demonstration as cd
from effect_networks.experiments.cans import CanModel, can_dataset, fit_can_network
from effect_networks.experiments.harness.config import ConfigError
from effect_networks.inference import compile as compile_queries
from effect_networks.inference import fit
from effect_networks.models.can_pyramid import can_network, can_rows, n_cans
from effect_networks.sim2d import field_throws, geometry

# A three-can world: 7 (cans 0, 1, 2) -> 3 (cans 0, 1) or 5 (cans 0, 2), both of two
# cans; only 3 -> 1 (can 0); 5 -> 0. Each rule is one field; every other field changes
# nothing.
RULES = {(7, 40): 3, (7, 41): 5, (3, 42): 1, (5, 43): 0, (1, 44): 0}


def hand_model() -> CanModel:
    """The can network fitted on every throwable field from each start, by ``RULES``."""
    throwable = [f for f in range(geometry.N_FIELDS) if field_throws.is_throwable(f, 0)]
    assert {f for _, f in RULES} <= set(throwable)
    starts = (7, 3, 5, 1)
    start = np.repeat(starts, len(throwable))
    field = np.tile(throwable, len(starts))
    end = np.array([RULES.get((s, f), s) for s, f in zip(start, field, strict=True)])
    net = can_network((0, 1, 3, 5, 7))
    params = fit(net, can_rows(net, start, field, end)).params
    mask = torch.zeros(geometry.N_FIELDS, dtype=torch.bool)
    mask[throwable] = True
    return CanModel(0, net, params, compile_queries(net, params), mask)


def test_a_hidden_configuration_is_resolved_by_the_throw_after_it():
    model = hand_model()
    configs = np.array([[7, 3, 1, 0], [7, 3, 1, 0], [7, 5, 5, 0]])
    seen = np.ones(configs.shape, dtype=bool)
    seen[0, 1] = False  # two cans, which two? only 3 -> 1 can follow: field 40 then 42
    best, probs, log_likelihood, implausible = cd.read_demonstrations(model, configs, seen)
    assert best[0, :2].tolist() == [40, 42] and best[1, :2].tolist() == [40, 42]
    assert best[2, 0] == 41 and best[2, 2] == 43  # 7 -> 5, (nothing), 5 -> 0
    assert best[:2, 2].tolist() == [44, 44]
    assert probs[0, 0, 40] > 0.95 and probs[2, 2, 43] > 0.95
    assert best[2, 1] != 43 and probs[2, 1, 43] < 0.01  # 43 would have cleared 5
    np.testing.assert_allclose(probs.sum(-1), 1.0, atol=1e-9)
    assert not probs[..., ~model.throwable.numpy()].any()  # the prior rules them out
    assert not implausible.any() and np.isfinite(log_likelihood).all()


@pytest.fixture(scope="module")
def tiny(tiny_data_dir):
    data = can_dataset(tiny_data_dir, "tiny", progress=False)
    sel = (data.angle == 0) & data.throwable
    return data, fit_can_network(data, 0), {int(c) for c in np.unique(data.start_config[sel])}


def test_the_thrown_demonstrations_keep_to_the_network_s_configurations(tiny):
    data, model, trained = tiny
    demos = cd.play_demonstrations(model, trained, 6, 3, 8, data.metadata["jitter"], seed=1)
    assert len(demos) == 6
    for configs, fields in demos:
        assert 1 <= len(fields) <= 3 and len(configs) == len(fields) + 1
        assert configs[0] in trained and configs[0] != 0
        assert all(model.throwable[f] for f in fields)
        assert all(a != b for a, b in zip(configs[:-1], configs[1:], strict=True))
        assert all(c in trained for c in configs[1:-1]) and configs[-1] in model.states
        assert all(n_cans(b) < n_cans(a) for a, b in zip(configs, configs[1:], strict=False))
    again = cd.play_demonstrations(model, trained, 6, 3, 8, data.metadata["jitter"], seed=1)
    assert again == demos


def test_the_experiment_at_the_tiny_scale(tiny_data_dir, tmp_path):
    config = cd.CanDemonstrationConfig(
        data_dir=tiny_data_dir, scale="tiny", n_demos=6, steps=3, tries=5, progress=False
    )
    result = cd.run_can_demonstration(config)
    assert result.n_demos == 6 and sum(result.lengths.values()) == 6
    assert result.throws["n"] == sum(int(k) * v for k, v in result.lengths.items())
    shares = [v for k, v in result.throws.items() if not k.startswith("n") and v is not None]
    assert all(0.0 <= v <= 1.0 for v in [*shares, *result.sequences.values()])
    s = result.shown
    assert len(s["configs"]) == len(s["fields"]) + 1 == len(s["probs"]) + 1 == len(s["seen"])
    assert s["seen"][0] and s["seen"][-1]
    for row in s["probs"]:
        assert sum(row) == pytest.approx(1.0)
    result.save(tmp_path)
    assert (tmp_path / "can_demonstration.png").stat().st_size > 10_000
    loaded = cd.CanDemonstrationResult.load(tmp_path / "can_demonstration.json")
    assert loaded.to_json() == result.to_json()
    assert "read back as fields" in loaded.to_markdown()


def test_config_refuses_bad_settings():
    with pytest.raises(ConfigError, match="^steps: 11 is out of range"):
        cd.CanDemonstrationConfig(steps=11)
    with pytest.raises(ConfigError, match="^hidden: 1.5 is out of range"):
        cd.CanDemonstrationConfig(hidden=1.5)
    with pytest.raises(ConfigError, match="^scale: "):
        cd.CanDemonstrationConfig(scale="huge")


def test_a_world_where_no_throw_is_kept_is_refused():
    # a network that knows only the three-can row: no throw that changes it is kept
    throwable = [f for f in range(geometry.N_FIELDS) if field_throws.is_throwable(f, 0)]
    net = can_network((7, 1023))  # the full pyramid: never the end of a throw from 7
    rows = np.full(len(throwable), 7)
    params = fit(net, can_rows(net, rows, np.array(throwable), rows)).params
    model = CanModel(0, net, params, compile_queries(net, params), hand_model().throwable)
    with pytest.raises(ValueError, match="^only 0 of 2 demonstrations after 40 starts"):
        cd.play_demonstrations(model, {7}, 2, 2, 1, 0.003, seed=0)

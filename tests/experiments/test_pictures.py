"""experiments.pictures: the can world's and the throw's figures with tiny settings."""

import pytest
from effect_networks.experiments.harness.config import ConfigError
from effect_networks.experiments.pictures import (
    CanWorldConfig,
    ThrowKinematicsConfig,
    draw_can_world,
    draw_throw_kinematics,
)


def test_can_world_pictures(tmp_path):
    pictures = draw_can_world(CanWorldConfig(frame_interval=0.25), tmp_path)
    assert set(pictures.files) == {"pyramid", "throw", "gif"}
    for path in pictures.files.values():
        assert (tmp_path / path.rsplit("/", 1)[-1]).stat().st_size > 1000
    assert "thrown off" in pictures.outcome


@pytest.mark.parametrize(
    ("field", "value", "words"),
    [
        ("config", 2**10, "integer in 0..1023"),
        ("config", 16, "not a physically possible configuration"),  # can 4 alone floats
        ("field", 0, "cannot be thrown"),  # the bottom row is below the ball's radius
        ("field", 195, "integer in 0..194"),
        ("jitter", 0.5, "expected a number in [0, 0.0033] m"),
        ("frame_interval", 0.0, "out of range"),
    ],
)
def test_can_world_config_names_the_field_at_fault(field, value, words):
    with pytest.raises(ConfigError, match=f"^{field}: ") as raised:
        CanWorldConfig(**{field: value})
    assert words in str(raised.value)


def test_throw_kinematics(tmp_path):
    result = draw_throw_kinematics(ThrowKinematicsConfig(grid=3, n=500), tmp_path)
    assert (tmp_path / "target_to_hit.png").stat().st_size > 0
    assert (tmp_path / "flight_paths.png").stat().st_size > 0
    assert 0.0 < result.clamped_share < 1.0
    with pytest.raises(ConfigError, match="^grid: "):
        ThrowKinematicsConfig(grid=1)

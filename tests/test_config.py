"""Config: defaults, YAML round trip, validation errors that name the field."""

import math

import pytest
import yaml

from ssp.config import PhysicsConfig, SearchConfig, SSPConfig, dump_config, load_config
from ssp.errors import ConfigError


def test_defaults_match_design():
    c = SSPConfig()
    assert c.physics.timestep == 0.005
    assert c.physics.solref == pytest.approx((0.01, 1.0))  # time constant 2 dt
    assert c.physics.solimp[:2] == (0.99, 0.999)
    assert c.data.inlier_radius == pytest.approx(0.0037)
    assert c.transition.sigma_rotation == pytest.approx(math.radians(18))
    assert c.temporal.static_translation == pytest.approx(0.0075)


def test_yaml_round_trip(tmp_path):
    c = SSPConfig()
    c.physics.timestep = 0.002
    c.library.decomposition.threshold = 0.08
    path = tmp_path / "ssp.yaml"
    path.write_text(dump_config(c))
    back = load_config(path)
    assert back == c
    assert back.physics.solref == pytest.approx((0.004, 1.0))


def test_partial_yaml_keeps_defaults(tmp_path):
    path = tmp_path / "p.yaml"
    path.write_text("forces:\n  gravity_fraction: 0.25\n")
    c = load_config(path)
    assert c.forces.gravity_fraction == 0.25
    assert c.forces.max_distance == SSPConfig().forces.max_distance


@pytest.mark.parametrize(
    "text, needle",
    [
        ("physics:\n  timestep: -1\n", "timestep"),
        ("physics:\n  time_step: 0.01\n", "time_step"),  # typo is rejected, not ignored
        ("library:\n  min_extent: 10\n", "min_extent"),
        ("- just\n- a list\n", "mapping"),
        ("physics: [unclosed\n", "YAML"),
    ],
)
def test_bad_config_names_the_problem(tmp_path, text, needle):
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError, match=needle):
        load_config(path)


def test_missing_file(tmp_path):
    with pytest.raises(ConfigError, match="cannot read"):
        load_config(tmp_path / "nope.yaml")


def _window_motion(c: SSPConfig) -> float:
    """What a search window can move an object (m), as SearchConfig's docstring puts it:
    ``w / dt`` quasi-static steps of at most ``g dt^2`` each, ``w g dt``."""
    w = c.search.settle_with_forces + c.search.settle_without_forces
    return w * c.physics.gravity * c.physics.timestep


def test_the_default_reach_covers_what_a_window_moves():
    c = SSPConfig()
    assert _window_motion(c) == pytest.approx(0.01226, abs=1e-5)  # 50 steps of 0.245 mm
    assert c.search.reach >= _window_motion(c)


@pytest.mark.parametrize(
    "search, physics",
    [
        ({"reach": 0.01}, {}),  # the default windows move up to 12.3 mm
        ({"settle_with_forces": 0.45, "settle_without_forces": 0.3}, {}),  # the reference's
        ({}, {"timestep": 0.01}),  # 25 steps of 0.98 mm
        ({"reach": 0.0}, {}),
    ],
    ids=["small-reach", "long-windows", "large-timestep", "no-reach"],
)
def test_a_reach_shorter_than_the_window_moves_is_rejected(tmp_path, search, physics):
    data = {"search": search, "physics": physics}
    c = SSPConfig.model_construct(search=SearchConfig(**search), physics=PhysicsConfig(**physics))
    bound = _window_motion(c)
    assert c.search.reach < bound
    with pytest.raises(ConfigError) as err:
        SSPConfig.from_dict(data, "ssp.yaml")
    msg = str(err.value)
    for name in ("search.reach", "search.settle_with_forces", "search.settle_without_forces"):
        assert name in msg
    assert "physics.timestep" in msg and f"{bound:.4g} m" in msg
    path = tmp_path / "ssp.yaml"  # the same from a YAML file
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(ConfigError, match=r"search\.reach .* less than what a search window"):
        load_config(path)


def test_a_reach_that_covers_the_windows_is_accepted():
    long = {"settle_with_forces": 0.45, "settle_without_forces": 0.3}
    c = SSPConfig.from_dict({"search": {**long, "reach": 0.04}})  # they move up to 36.8 mm
    assert c.search.reach == 0.04
    at = SSPConfig.from_dict({"search": {"reach": _window_motion(SSPConfig())}})  # the bound
    assert at.search.reach == pytest.approx(0.01226, abs=1e-5)
    none = {k: 0.0 for k in ("settle_with_forces", "settle_without_forces")}
    assert SSPConfig.from_dict({"search": {**none, "reach": 0.0}}).search.reach == 0.0

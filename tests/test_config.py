"""Config: defaults, YAML round trip, validation errors that name the field."""

import math

import pytest

from ssp.config import SSPConfig, dump_config, load_config
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
    dump_config(c, path)
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

"""The shipped parameter files hold every setting the nodes declare, with its default."""

from pathlib import Path

import pytest
import yaml

from robot_ct_ros.ct.calibration import CalibrationSettings
from robot_ct_ros.parameters import ros_defaults

CONFIG = Path(__file__).resolve().parents[1] / "config"


@pytest.mark.parametrize("node, exclude", [("recon_service", ()), ("replay", ("method",))])
def test_node_yaml_lists_every_calibration_setting_with_its_default(node, exclude):
    params = yaml.safe_load((CONFIG / f"{node}.yaml").read_text())[f"/**/{node}"]["ros__parameters"]
    for name, default in ros_defaults(CalibrationSettings).items():
        if name in exclude:
            continue
        assert name in params, f"config/{node}.yaml lacks {name}: python -m robot_ct_ros.nodes.config_files"
        assert params[name] == (pytest.approx(default) if isinstance(default, float) else default), name


def test_recon_service_yaml_lists_the_services_own_settings():
    from robot_ct_ros.jobs.online import ServiceSettings

    params = yaml.safe_load((CONFIG / "recon_service.yaml").read_text())["/**/recon_service"]["ros__parameters"]
    for name, default in ros_defaults(ServiceSettings).items():
        assert params[name] == default, name


@pytest.mark.parametrize("node, cls", [("recorder", "robot_ct_ros.nodes.recorder:RecorderSettings"),
                                       ("replay", "robot_ct_ros.nodes.replay:ReplaySettings")])
def test_recorder_and_replay_yaml_list_their_typed_settings(node, cls):
    import importlib

    module, name = cls.split(":")
    settings = getattr(importlib.import_module(module), name)
    params = yaml.safe_load((CONFIG / f"{node}.yaml").read_text())[f"/**/{node}"]["ros__parameters"]
    for key, default in ros_defaults(settings).items():
        assert key in params, f"config/{node}.yaml lacks {key}"
        assert params[key] == default, key


@pytest.mark.parametrize("node, exclude", [("recon_service", ()), ("replay", ("method",))])
def test_the_shipped_file_gives_the_library_s_defaults_exactly(node, exclude):
    """A node started from its config file ran with a prior of 0.30000001398 deg (the file rounded the radians
    to 9 digits), so its corrected geometry differed from robot-ct calibrate's with the same settings."""
    from robot_ct_ros.parameters import from_ros_values

    params = yaml.safe_load((CONFIG / f"{node}.yaml").read_text())[f"/**/{node}"]["ros__parameters"]
    values = {k: v for k, v in params.items() if k in ros_defaults(CalibrationSettings)}
    values |= {k: ros_defaults(CalibrationSettings)[k] for k in exclude}  # replay's method is its own parameter
    assert from_ros_values(CalibrationSettings, values) == CalibrationSettings()
    assert from_ros_values(CalibrationSettings, ros_defaults(CalibrationSettings)) == CalibrationSettings()


def test_a_refused_choice_shows_an_empty_choice_as_such():
    """replay's method:=bogus said "method must be one of , none, ...": the empty choice (no offline job) showed
    as a blank."""
    from robot_ct_ros.nodes.replay import ReplaySettings

    with pytest.raises(ValueError, match=r'method must be one of "", none, ') as err:
        ReplaySettings(method="bogus")
    assert "got 'bogus'" in str(err.value)

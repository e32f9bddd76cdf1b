"""Every setting is checked when the config is loaded or a flag sets it: its type, finite,
in its declared range or set; the error names the key and the file (or the flag)."""

from __future__ import annotations

import dataclasses

import pytest

from fleetslam import cli
from fleetslam.config import Config, load_config


def test_every_setting_declares_its_rule_and_its_default_keeps_it():
    from fleetslam.validation.rules import checked, rules_of

    config = Config()
    undeclared = []
    for section in dataclasses.fields(config):
        values = getattr(config, section.name)
        for key, (hint, rule) in rules_of(type(values)).items():
            if hint is not bool and rule is None:  # a bool's type is its whole rule
                undeclared.append(f"{section.name}.{key}")
            assert checked(getattr(values, key), hint, rule) == getattr(values, key), key
    assert not undeclared, f"settings without a declared range or choice: {undeclared}"


@pytest.mark.parametrize("section, key, toml, problem", [
    # The attack's cases: a hung robot, a refused session count, ZeroDivisionError, cv2.error.
    ("transport", "max_queued_frames", "0", "must be at least 1"),
    ("transport", "max_sessions", "-1", "must be at least 1"),
    ("map", "pixel_stride", "0", "must be at least 1"),
    ("orb", "n_features", "-5", "must be in [1, 1000000]"),
    ("tracking", "match_ratio", "nan", "must be a finite number"),
    ("link", "bandwidth_mbps", "inf", "must be a finite number"),
    ("link", "loss", "1.5", "must be in [0, 1)"),
    # Types: no "invalid literal for int()", no bool for an int, no int for a bool.
    ("orb", "n_features", '"12x"', "expected an integer"),
    ("orb", "n_features", "12.5", "expected an integer"),
    ("orb", "n_features", "true", "expected an integer"),
    ("loop_closing", "enabled", "1", "expected true or false"),
    ("planner", "objective", "3", "expected a string"),
    # Sets and shapes.
    ("tracking", "local_mapping", '"sometimes"', "must be one of async, inline"),
    ("wire", "frame_image_codec", '"gif"', "must be one of png, jpeg"),
    ("tracking", "local_ba_iterations", "[5]", "expected a list of 2 values"),
    ("planner", "online_points", "[0, 4]", "4 must be in [0, 3]"),
    ("transport", "endpoint", '"foo"', "not PROTOCOL/ADDRESS"),
    ("source", "ros_endpoint", '"tcp/localhost:0"', "port '0' is not a number in 1..65535"),
    ("placement", "worker_id", '"a b"', "must be 1..64 characters of [A-Za-z0-9_-]"),
    ("view", "server_memory_limit", '"lots"', "must be a size such as 1GiB"),
    ("view", "grpc_bind", '"127.0.0.1:80"', "is not a host name or an IP address"),
])
def test_a_bad_setting_in_toml_names_key_and_file(tmp_path, section, key, toml, problem):
    path = tmp_path / "bad.toml"
    path.write_text(f"[{section}]\n{key} = {toml}\n")
    with pytest.raises(ValueError) as err:
        load_config(path)
    message = str(err.value)
    assert message.startswith(f"{path}: {section}.{key} = ") and problem in message
    assert "\n" not in message


def test_good_values_load_as_their_type(tmp_path):
    # c_total_g is optional (None by default): its type is the one declared, not None's.
    path = tmp_path / "good.toml"
    path.write_text("[link]\nbandwidth_mbps = 5\n[planner]\nonline_points = [0, 3]\n"
                    "c_total_g = 2\n")
    config = load_config(path)
    assert config.link.bandwidth_mbps == 5.0 and isinstance(config.link.bandwidth_mbps, float)
    assert config.planner.online_points == (0, 3)
    assert config.planner.c_total_g == 2.0 and isinstance(config.planner.c_total_g, float)


def test_the_command_line_says_which_file_and_key_in_one_line(tmp_path, capsys):
    path = tmp_path / "bad.toml"
    path.write_text("[transport]\nmax_queued_frames = 0\n")
    assert cli.main(["--config", str(path), "status"]) == 2
    err = capsys.readouterr().err
    assert err == (f"fleetslam: error: {path}: transport.max_queued_frames = 0: must be at "
                   f"least 1\n")


@pytest.mark.parametrize("argv, message", [
    (["robot", "--id", "r1", "--source", "nowhere", "--bandwidth-mbps", "nan"],
     "--bandwidth-mbps nan: must be a finite number"),
    (["robot", "--id", "r1", "--source", "nowhere", "--loss", "-0.5"],
     "--loss -0.5: must be in [0, 1)"),
    (["robot", "--id", "r1", "--source", "nowhere", "--link-seed", "-1"],
     "--link-seed -1: must be at least 0"),
    (["demo", "--frames", "0"], "--frames 0: must be at least 1"),
    (["plan", "--paper", "--bandwidth-mbps", "inf"],
     "--bandwidth-mbps inf: must be a finite number"),
    (["plan", "--paper", "--latency-ms", "-3"], "--latency-ms -3.0: must be at least 0"),
])
def test_a_flag_is_checked_like_the_setting_it_sets(argv, message, capsys):
    assert cli.main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("fleetslam: error: ") and message in err and err.count("\n") == 1


def test_a_config_file_that_is_not_utf8_is_named(tmp_path):
    from fleetslam.config import load_config

    path = tmp_path / "bad.toml"
    path.write_bytes(b"[grid]\nresolution_m = 0.05 # \xff\xfe\n")
    with pytest.raises(ValueError, match=r"bad.toml: cannot read config: 'utf-8' codec"):
        load_config(path)

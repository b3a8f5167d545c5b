"""Rig YAML values: a rig: sim file's grasp section, which the twin would ignore (it grasps with its own control), is
one error naming the file and the key; a number written without a dot (``1e-9``, which YAML reads as a string) is
the number in every number field, as in ``reconstruct --config``, and a word is still refused."""

import dataclasses

import pytest
import yaml

from tacsplat.acquisition.config import TWIN_GRASP, GraspControl, RigConfig, example_rig, load_rig, validate
from tacsplat.cli import main
from tacsplat.errors import ConfigError


def _write(tmp_path, name: str, changes: dict, unquote: str | None = None):
    """The shipped rig file ``name`` with ``changes`` (``"grasp/poll_s": value``), as ``rig.yaml``; ``unquote``: a
    string value written bare, as a person types it (YAML still reads ``1e-9`` as a string)."""
    data = yaml.safe_load(example_rig(name).read_text())
    for dotted, value in changes.items():
        node = data
        *parents, last = dotted.split("/")
        for p in parents:
            node = node[int(p)] if isinstance(node, list) else node.setdefault(p, {})
        node[last] = value
    text = yaml.safe_dump(data)
    if unquote is not None:
        text = text.replace(f"'{unquote}'", unquote)
        assert f" {unquote}\n" in text or f"[{unquote}," in text, text
        assert yaml.safe_load(unquote) == unquote  # written bare, YAML still reads it as a string
    path = tmp_path / "rig.yaml"
    path.write_text(text)
    return path


# --- a rig: sim file's grasp section ----------------------------------------------------------------


@pytest.mark.parametrize(
    "grasp, key",
    [
        ({"close_speed_rad_s": 10.0}, "grasp.close_speed_rad_s"),
        ({"poll_s": 1.0}, "grasp.poll_s"),
        ({"poll_s": 0.02}, "grasp.poll_s"),  # GraspControl's default, still not the twin's
        ({"max_close_s": 60, "settle_polls": 1000}, "grasp.max_close_s"),  # the first in the file
        ({"close_pose": [0.0] * 16}, "grasp.close_pose"),
    ],
)
@pytest.mark.parametrize("command", [["sim-capture", "--rig"], ["capture", "--rig"]])
def test_a_sim_rig_that_sets_the_grasp_control_is_one_error_naming_file_and_key(tmp_path, capsys, grasp, key, command):
    rig = _write(tmp_path, "sim", {"grasp": grasp})
    out = tmp_path / "scene"
    assert main([*command, str(rig), "--out", str(out)]) == 1
    err = capsys.readouterr().err.strip()
    assert err == f"error: {rig}: {key}: {TWIN_GRASP}", err
    assert not out.exists()


def test_a_sim_rig_with_an_empty_grasp_section_loads_and_a_real_rig_keeps_its_grasp_control(tmp_path):
    (tmp_path / "empty.yaml").write_text("rig: sim\ngrasp:\n")
    (tmp_path / "braces.yaml").write_text("rig: sim\ngrasp: {}\n")
    assert load_rig(tmp_path / "empty.yaml").grasp == load_rig(tmp_path / "braces.yaml").grasp == GraspControl()
    mock = load_rig(_write(tmp_path, "mock", {"grasp/poll_s": 0.005}), mock=True)
    assert mock.grasp.poll_s == 0.005


# --- numbers YAML reads as strings ------------------------------------------------------------------


@pytest.mark.parametrize(
    "name, key, text, value",
    [
        ("mock", "grasp/poll_s", "1e-9", 1e-9),
        ("mock", "grasp/close_pose", [0.0, "1e-1", *[0.0] * 14], [0.0, 0.1, *[0.0] * 14]),
        ("mock", "board/square_length_m", "15e-3", 0.015),
        ("mock", "camera/fps", "3e1", 30.0),
        ("mock", "mock_devices/tactile_pixel_size_m", "16e-5", 1.6e-4),
        ("mock", "sim/true_errors/joint_offsets_rad/index_1", "5e-2", 0.05),
        ("sim", "sim/object_radius", "8e-2", 0.08),
        ("sim", "plan/views/radius_m", "3E-1", 0.3),
        ("sim", "sim/true_errors/hand_eye/translation_m", ["3e-3", 0.0, 0.0], [0.003, 0.0, 0.0]),
        ("sim", "plan/grasps/count", "2e0", 2),  # an int field takes a whole number, as reconstruct --config
    ],
)
def test_a_number_written_without_a_dot_is_the_number(tmp_path, name, key, text, value):
    bare = text if isinstance(text, str) else next(t for t in text if isinstance(t, str))
    config = load_rig(_write(tmp_path, name, {key: text}, unquote=bare), mock=name == "mock")
    got = config
    for part in key.split("/"):
        got = got[part] if isinstance(got, dict) else getattr(got, part)
    assert (list(got) if isinstance(value, list) else got) == value
    assert type(got) is type(value) or all(type(x) is float for x in got)  # (an int field holds an int)


@pytest.mark.parametrize(
    "key, text, told",
    [
        ("grasp/poll_s", "fast", "grasp.poll_s: expected a finite number, got 'fast'"),
        ("grasp/poll_s", "inf", "grasp.poll_s: expected a finite number, got 'inf'"),
        ("grasp/close_pose", [0.0, "half", *[0.0] * 14], "grasp.close_pose[1]: expected a finite number, got 'half'"),
        ("plan/grasps/count", "2.5e0", "plan.grasps.count: expected an integer, got '2.5e0'"),
        ("grasp/poll_s", "2e0", "grasp.poll_s: must be in (0, 1] s, got 2"),  # read, then checked as any number
    ],
)
def test_a_word_or_a_number_out_of_range_is_still_refused_naming_the_field(tmp_path, key, text, told):
    bare = text if isinstance(text, str) else next(t for t in text if isinstance(t, str))
    path = _write(tmp_path, "mock", {key: text}, unquote=bare)
    with pytest.raises(ConfigError) as err:
        load_rig(path, mock=True)
    assert str(err.value) == f"{path}: {told}"


def test_a_string_field_keeps_a_number_like_text_and_a_config_built_in_code_gets_no_reading(tmp_path):
    assert load_rig(_write(tmp_path, "sim", {"object": "1e5"}, unquote="1e5")).object == "1e5"
    with pytest.raises(ConfigError) as err:  # a string in code is a bug, not a YAML reading
        validate(dataclasses.replace(RigConfig(rig="sim"), grasp=GraspControl(poll_s="1e-3")))
    assert err.value.key == "grasp.poll_s" and "expected a finite number, got '1e-3'" in str(err.value)

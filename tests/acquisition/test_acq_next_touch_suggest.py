"""The operator session's suggestion (`tacsplat capture --suggest RUN`, key s): from a reconstruction in progress of
the capture, where a fingertip should touch and from which direction, drawn on the wrist camera's image; without a
checkpoint yet, a message and the session goes on."""

import io
import re
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from tacsplat.acquisition.config import load_rig
from tacsplat.acquisition.operator_session import run_capture
from tacsplat.reconstruction.config import TrainConfig
from tacsplat.reconstruction.trainer import reconstruct

sys.path.insert(0, str(Path(__file__).parent))
from acq_helpers import ScriptedKeys  # noqa: E402

pytestmark = pytest.mark.timeout(300)


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    """Three train views of the bell taken in the session on the twin, and a brief reconstruction of them."""
    root = tmp_path_factory.mktemp("suggest")
    rig = root / "sim.yaml"
    rig.write_text(
        yaml.safe_dump(
            {
                "rig": "sim",
                "object": "bell",
                "sim": {"object": "bell", "resolution": 64, "seed": 2},
                "plan": {
                    "views": {"train": 3, "test": 0, "mode": "hemisphere"},
                    "grasps": {"count": 1, "mode": "random"},
                },
            }
        )
    )
    config = load_rig(rig)
    assert run_capture(config, root / "scene", keys=ScriptedKeys("\n\n\nq"), output=io.StringIO()) == 1
    reconstruct(root / "scene", root / "run", TrainConfig(iterations=30, device="cpu"), show_progress=False)
    return config, root


def test_s_suggests_a_touch_on_the_object_drawn_on_the_camera_image(capture):
    config, root = capture
    output = io.StringIO()
    assert (
        run_capture(config, root / "scene", resume=True, keys=ScriptedKeys("sq"), output=output, suggest=root / "run")
        == 1
    )
    text = output.getvalue()
    assert "[s] suggest a grasp" in text
    found = re.search(
        r"suggested grasp: touch at \((\S+), (\S+), (\S+)\) m in the world frame, approaching from "
        r"azimuth (\S+) deg, elevation (\S+) deg; (\d+) mm\^2 of uncertain surface under the fingertip; "
        r"picture: (\S+)",
        text,
    )
    assert found, text
    target = np.array([float(found[i]) for i in (1, 2, 3)])
    azimuth, elevation = np.radians(float(found[4])), np.radians(float(found[5]))
    towards_hand = np.array(
        [np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth), np.sin(elevation)]
    )
    assert np.linalg.norm(target) < 0.1  # on the bell (bounding radius 0.08 at the origin) ...
    assert target @ towards_hand > 0  # ... on the side the fingertip comes from
    assert int(found[6]) > 0
    picture = Path(found[7])
    assert picture == root / "scene-suggestion.png"
    drawn = cv2.imread(str(picture))[..., ::-1]
    magenta = (drawn[..., 0] > 200) & (drawn[..., 1] < 60) & (drawn[..., 2] > 200)
    assert drawn.shape == (64, 64, 3) and magenta.sum() >= 20  # the patch ringed on the last view's image


def test_without_a_checkpoint_yet_the_session_says_so_and_goes_on(capture, tmp_path):
    config, root = capture
    output = io.StringIO()
    code = run_capture(
        config, root / "scene", resume=True, keys=ScriptedKeys("s\nq"), output=output, suggest=tmp_path / "empty-run"
    )
    text = output.getvalue()
    assert code == 1 and "no suggestion:" in text and "checkpoint" in text, text
    assert "all 3 train and 0 test views of the plan are taken" in text  # the next key was served


def test_s_is_no_key_without_suggest(capture):
    config, root = capture
    output = io.StringIO()
    run_capture(config, root / "scene", resume=True, keys=ScriptedKeys("sq"), output=output)
    text = output.getvalue()
    assert "[s] suggest" not in text and "suggested grasp" not in text and "no suggestion" not in text

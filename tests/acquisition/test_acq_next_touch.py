"""Grasp selection on a hand-made reconstruction: a sphere of Gaussians that every camera sees from +x only. The
predicted contact patch of a fingertip lies on the sphere where its normal meets it; the selector prefers the side
no view sees; a grasp repeated where touches already are scores lower than a new one."""

import sys
from pathlib import Path

import numpy as np
import pytest

from tacsplat.acquisition.next_touch import Belief, Candidate, Pad, PatchModel, predict_patch, rank_candidates
from tacsplat.datasets import SensorModel
from tacsplat.geometry import make_pose
from tacsplat.reconstruction.uncertainty import SCORES, gaussian_uncertainty

sys.path.insert(0, str(Path(__file__).parents[1] / "reconstruction"))  # the hand-made sphere of the recon tests
from recon_synthetic import RADIUS  # noqa: E402
from test_recon_uncertainty import _sphere, _views_from_plus_x  # noqa: E402

SENSOR = SensorModel("sim-digit", 160, 128, 0.00015, 0.002)  # the twin's pad: 24 x 19 mm


def _pad_facing(direction, gap: float = 0.01, finger: str = "index") -> Pad:
    """A pad ``gap`` metres off the sphere on the side of ``direction``, its normal (z) pointing at the centre."""
    d = np.asarray(direction, float) / np.linalg.norm(direction)
    z = -d
    helper = np.array([0.0, 0.0, 1.0]) if abs(z[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    return Pad(finger, make_pose(np.stack([x, np.cross(z, x), z], axis=1), d * (RADIUS + gap)))


@pytest.fixture(scope="module", params=SCORES)
def belief(request) -> Belief:
    g = _sphere()
    return Belief(g, gaussian_uncertainty(g, _views_from_plus_x(), request.param))


def test_a_patch_lies_on_the_sphere_where_the_pad_normal_meets_it(belief):
    patch = predict_patch(belief, _pad_facing((0, 1, 0), gap=0.012), PatchModel.of_sensor(SENSOR))
    assert patch is not None and len(patch.points) >= 5
    radii = np.linalg.norm(patch.points, axis=1)
    assert np.abs(radii - RADIUS).max() < 0.003  # on the surface (the flat Gaussians' blended depth)
    assert patch.points[:, 1].min() > 0.8 * RADIUS  # around the pole the pad faces, within the contact depth
    assert abs(patch.distance_m - 0.012) < 0.003  # how far the pad travels to the contact
    assert predict_patch(belief, _pad_facing((0, 1, 0), gap=0.2), PatchModel.of_sensor(SENSOR)) is None  # out of reach


def test_the_selector_prefers_the_side_no_view_sees(belief):
    model = PatchModel.of_sensor(SENSOR)
    seen = Candidate(0, [_pad_facing((1, 0.2, 0), finger=f) for f in ("index", "thumb")], np.array([1.0, 0, 0]))
    unseen = Candidate(1, [_pad_facing((-1, 0.2, 0), finger=f) for f in ("index", "thumb")], np.array([-1.0, 0, 0]))
    ranked = rank_candidates(belief, [seen, unseen], model)
    assert [r.candidate.index for r in ranked] == [1, 0]
    assert ranked[0].score > 2 * ranked[1].score > 0


def test_a_repeated_grasp_scores_lower_than_a_new_one(belief):
    model = PatchModel.of_sensor(SENSOR)
    first = Candidate(0, [_pad_facing((-1, 0.3, 0.2))], np.array([-1.0, 0.3, 0.2]))
    other = Candidate(1, [_pad_facing((-1, -0.3, -0.2))], np.array([-1.0, -0.3, -0.2]))
    before = {r.candidate.index: r.score for r in rank_candidates(belief, [first, other], model)}
    assert before[0] == pytest.approx(before[1], rel=0.5)  # two equally unknown places
    touched = predict_patch(belief, first.pads[0], model).points  # the first grasp's touches, where it predicted
    after = rank_candidates(Belief(belief.gaussians, belief.uncertainty, touched), [first, other], model)
    assert [r.candidate.index for r in after] == [1, 0]
    assert after[1].score < 0.1 * before[0]  # what the first grasp touched is known now
    assert after[0].score == pytest.approx(before[1], rel=0.05)  # the other place is as unknown as before


def test_ties_go_to_the_lower_candidate_and_missing_pads_score_nothing(belief):
    model = PatchModel.of_sensor(SENSOR)
    pad = _pad_facing((-1, 0, 0))
    nothing = Candidate(2, [_pad_facing((-1, 0, 0), gap=0.3)], np.array([-1.0, 0, 0]))
    ranked = rank_candidates(
        belief, [Candidate(5, [pad], -np.ones(3)), nothing, Candidate(3, [pad], -np.ones(3))], model
    )
    assert [r.candidate.index for r in ranked] == [3, 5, 2]
    assert ranked[2].score == 0.0 and ranked[2].patches == []

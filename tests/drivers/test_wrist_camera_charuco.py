"""Wrist camera: ChArUco boards rendered with cv2.aruco, warped by known poses through a known (distorted) camera."""

import cv2
import numpy as np
import pytest

from tacsplat.cli import main as tacsplat_main
from tacsplat.drivers import Camera
from tacsplat.drivers.wrist_camera import (
    T_WORLD_BOARD,
    CameraCalibration,
    CharucoBoardSpec,
    WristCamera,
    board_pose,
    calibrate_intrinsics,
    detect_charuco,
    hand_eye_calibration,
    tacsplat_K_from_opencv,
)
from tacsplat.geometry import invert_pose, look_at, make_pose, project_points, rotation_angle_between

pytestmark = pytest.mark.timeout(120)

W, H = 640, 480
K_TRUE = np.array([[600.0, 0.0, 322.0], [0.0, 605.0, 238.0], [0.0, 0.0, 1.0]])  # tacsplat convention (+0.5)
DIST_TRUE = np.array([-0.28, 0.09, 0.0005, -0.0003, 0.0])  # a wide-angle webcam
SPEC = CharucoBoardSpec()
SUPERSAMPLE = 3
BOARD_PX = 100  # board image pixels per square


def _shift(d):
    return np.array([[1.0, 0.0, d], [0.0, 1.0, d], [0.0, 0.0, 1.0]])


class BoardRenderer:
    """Exact images of the planar board: homography of the board image, optional lens distortion, box filter."""

    def __init__(self, distort: bool):
        self.board_img = SPEC.board().generateImage(
            (SPEC.squares_x * BOARD_PX, SPEC.squares_y * BOARD_PX), marginSize=0
        )
        self.metres_per_px = SPEC.square_length_m / BOARD_PX
        self.K_hi = np.diag([SUPERSAMPLE, SUPERSAMPLE, 1.0]) @ K_TRUE  # continuous coords scale exactly
        self.maps = None
        if distort:
            K_cv = _shift(-0.5) @ self.K_hi  # OpenCV convention for OpenCV
            self.maps = cv2.initInverseRectificationMap(
                K_cv, DIST_TRUE, None, K_cv, (W * SUPERSAMPLE, H * SUPERSAMPLE), cv2.CV_32FC1
            )

    def __call__(self, T_cam_board):
        # board pixel centre (a, b) (continuous, +0.5) -> board metres (s a, s b, 0) -> camera pixel (continuous)
        Hc = self.K_hi @ np.column_stack([T_cam_board[:3, 0], T_cam_board[:3, 1], T_cam_board[:3, 3]])
        Hc = Hc @ np.diag([self.metres_per_px, self.metres_per_px, 1.0])
        H_cv = _shift(-0.5) @ Hc @ _shift(0.5)  # warpPerspective works with integer pixel centres
        big = cv2.warpPerspective(
            self.board_img, H_cv, (W * SUPERSAMPLE, H * SUPERSAMPLE), flags=cv2.INTER_LINEAR, borderValue=160
        )
        if self.maps is not None:
            big = cv2.remap(big, self.maps[0], self.maps[1], cv2.INTER_LINEAR, borderValue=160)
        return cv2.resize(big, (W, H), interpolation=cv2.INTER_AREA)


def random_views(n, seed):
    rng = np.random.default_rng(seed)
    centre = np.array([0.105, 0.075, 0.0])  # board centre, OpenCV board frame (z into the board)
    poses = []
    for _ in range(n):
        eye = centre + np.array([rng.uniform(-0.16, 0.16), rng.uniform(-0.12, 0.12), -rng.uniform(0.27, 0.4)])
        T_board_cam = look_at(eye, centre + rng.normal(0, 0.01, 3), up=(rng.normal(0, 0.2), -1.0, 0.0))
        poses.append(invert_pose(T_board_cam))  # T_cam_board
    return poses


@pytest.fixture(scope="module")
def distorted():
    render = BoardRenderer(distort=True)
    poses = random_views(14, seed=1)
    return poses, [render(T) for T in poses]


@pytest.fixture(scope="module")
def calibration(distorted):
    poses, images = distorted
    return calibrate_intrinsics(images[:11], SPEC)


def test_charuco_calibration_recovers_focal_length(calibration):
    fx, fy = calibration.K_opencv[0, 0], calibration.K_opencv[1, 1]
    assert abs(fx - K_TRUE[0, 0]) / K_TRUE[0, 0] < 0.01
    assert abs(fy - K_TRUE[1, 1]) / K_TRUE[1, 1] < 0.01
    assert calibration.rms_px < 0.5
    assert calibration.dist[0] == pytest.approx(DIST_TRUE[0], abs=0.04)


def test_pnp_recovers_held_out_poses(distorted, calibration):
    poses, images = distorted
    for T_cam_board, image in zip(poses[11:], images[11:]):
        T_world_cam, rms, corners, _ = board_pose(image, SPEC, calibration.K_opencv, calibration.dist)
        assert corners >= 12 and rms < 0.5
        T_world_cam_true = T_WORLD_BOARD @ invert_pose(T_cam_board)
        angle = np.degrees(rotation_angle_between(T_world_cam[:3, :3], T_world_cam_true[:3, :3]))
        assert angle < 0.5
        t_err = np.linalg.norm(T_world_cam[:3, 3] - T_world_cam_true[:3, 3])
        assert t_err < 0.01 * np.linalg.norm(T_world_cam_true[:3, 3])
        assert T_world_cam[2, 3] > 0  # world z is up: the camera looks down on the face-up board


def test_pixel_centre_convention_is_converted_once():
    # OpenCV projection (integer centres) + 0.5 == tacsplat projection with the converted K
    K_cv = np.array([[500.0, 0.0, 300.3], [0.0, 510.0, 200.7], [0.0, 0.0, 1.0]])
    pts = np.random.default_rng(0).uniform([-0.1, -0.1, 0.5], [0.1, 0.1, 1.0], (20, 3))
    uv_cv, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), K_cv, None)
    uv, _ = project_points(pts, tacsplat_K_from_opencv(K_cv), np.eye(4))
    np.testing.assert_allclose(uv, uv_cv.reshape(-1, 2) + 0.5, atol=1e-9)
    # detected corners in an exactly rendered view sit where tacsplat's K projects them, minus 0.5
    T_cam_board = random_views(1, seed=7)[0]
    image = BoardRenderer(distort=False)(T_cam_board)
    obj, img = detect_charuco(image, SPEC.board())
    uv, _ = project_points(obj, K_TRUE, invert_pose(T_cam_board))
    offset = (img - uv).mean(axis=0)
    np.testing.assert_allclose(offset, [-0.5, -0.5], atol=0.05)


def test_wrist_camera_reads_undistorted_frames_from_video(distorted, calibration, tmp_path):
    poses, images = distorted
    path = tmp_path / "wrist.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"FFV1"), 30.0, (W, H))
    assert writer.isOpened()
    for image in images[11:]:
        writer.write(cv2.cvtColor(image, cv2.COLOR_GRAY2BGR))
    writer.release()
    calib_file = tmp_path / "camera.json"
    calibration.save(calib_file)
    with WristCamera(str(path), calib_file) as camera:
        assert isinstance(camera, Camera)
        rgb, stamp = camera.read()
        assert rgb.shape == (H, W, 3) and rgb.dtype == np.uint8 and stamp > 0
        # an undistorted image is a pinhole image with camera.K: zero-distortion PnP fits it to a fraction of a
        # pixel, while the raw frame does not fit a pinhole model
        T_world_cam, rms = camera.pose_in_world(rgb)
        assert rms < 0.3
        K_cv_raw = calibration.K_opencv
        rms_raw = board_pose(images[11], SPEC, K_cv_raw, None).rms_px
        assert rms_raw > 3 * rms
        T_world_cam_true = T_WORLD_BOARD @ invert_pose(poses[11])
        assert np.degrees(rotation_angle_between(T_world_cam[:3, :3], T_world_cam_true[:3, :3])) < 0.5
        # and tacsplat's K (pixel centres at +0.5) projects the corners onto the detections + 0.5
        obj, img = detect_charuco(rgb, SPEC.board())
        uv, _ = project_points(obj @ T_WORLD_BOARD[:3, :3].T, camera.K, T_world_cam)
        assert np.sqrt(np.mean(np.sum((img + 0.5 - uv) ** 2, axis=1))) < 0.3


def test_hand_eye_recovers_the_camera_mount():
    rng = np.random.default_rng(3)
    T_hand_cam = make_pose(cv2.Rodrigues(np.array([0.1, -0.2, 0.3]))[0], [0.03, -0.02, 0.08])
    T_base_world = make_pose(cv2.Rodrigues(np.array([0.0, 0.0, 0.5]))[0], [0.6, 0.1, -0.05])
    T_base_hand, T_world_cam = [], []
    for _ in range(8):
        T = make_pose(cv2.Rodrigues(rng.normal(0, 0.5, 3))[0], rng.uniform(-0.2, 0.2, 3) + [0.4, 0, 0.3])
        T_base_hand.append(T)
        T_world_cam.append(invert_pose(T_base_world) @ T @ T_hand_cam)
    T = hand_eye_calibration(T_base_hand, T_world_cam)
    np.testing.assert_allclose(T, T_hand_cam, atol=1e-6)


def test_calibrate_camera_command(distorted, tmp_path, capsys):
    _, images = distorted
    folder = tmp_path / "board"
    folder.mkdir()
    for i, image in enumerate(images[:8]):
        cv2.imwrite(str(folder / f"view_{i:02d}.png"), image)
    out = tmp_path / "camera.json"
    assert tacsplat_main(["calibrate", "camera", str(folder), "--out", str(out)]) == 0
    assert "RMS reprojection error" in capsys.readouterr().out
    calib = CameraCalibration.load(out)
    assert abs(calib.K_opencv[0, 0] - K_TRUE[0, 0]) / K_TRUE[0, 0] < 0.01
    assert len(calib.per_image_rms_px) == 8
    assert cv2.imread(str(out.with_suffix(".png"))) is not None

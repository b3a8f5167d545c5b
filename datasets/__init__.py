"""tacsplat.datasets: the scene directory format (DESIGN.md).

A scene directory is what acquisition, the simulator and the importers write
(all through :class:`SceneWriter`) and the only thing reconstruction reads
(through :class:`Scene`)::

    scene/
      transforms.json  nerfstudio input: camera_model "OPENCV", fl_x fl_y cx cy w h
                       (per frame instead when frames differ), k1 k2 p1 p2 = 0,
                       frames [{id, file_path, transform_matrix (OpenGL
                       camera-to-world), split: train | test, mask_path
                       (optional: on every frame or none)}], and the
                       train_filenames / val_filenames / test_filenames lists
                       (val = test) that make nerfstudio keep our split
      images/          000000.png ...  RGB uint8, undistorted
      masks/           000000.png ...  optional greyscale uint8, 255 = use the pixel
      touches.json     {"sensor": {name, width_px, height_px, pixel_size_m,
                       gel_thickness_m} | null, "touches": [{id, grasp, finger,
                       depth_file, T_world_sensor, in_contact, hand_file
                       (optional: the grasp's hand motion)}]}
      touches/         000000.npz ...  key "depth": float32 [h, w] metres of
                       indentation (0 = no contact)
      grasps/          000000.npz ...  one per grasp of a hand capture: the
                       joint trajectory and the hand's boxes (HandMotion)
      scene.json       provenance: format, source (sim | real | import), object,
                       units "m", capture_plan, extra, tacsplat_version, created,
                       gt {mesh, depth {frame id: file}}, annotations {key:
                       plain JSON} (e.g. next_touch: next-best's decisions),
                       sparse_points (only where the scene has them)
      points3D.ply     optional: an import's SfM points (x y z float64 metres,
                       red green blue uchar), where training's G_c start
      gt/              evaluation only, never read by training: mesh.ply and
                       depth/<frame id>.npz (key "depth", z-depth in metres)
      journal.jsonl    the writer's append-only log the index files are
                       materialised from (see :mod:`tacsplat.datasets.writer`)

Inside the code poses are OpenCV camera-to-world (``Frame.T_world_cam``) in
metres; the OpenGL matrices of nerfstudio and Blender are converted only in
this package. Importers, each in its own module so that importing the package
loads neither OpenCV (imported where an image is read or written) nor pycolmap:
``datasets.blender.import_blender`` (NeRF-synthetic
/ Shiny Blender), ``datasets.colmap.import_colmap`` (COLMAP sparse models through
pycolmap), ``datasets.nerfstudio.import_nerfstudio`` (nerfstudio / instant-ngp
``transforms.json``); :func:`copy_scene` writes a copy of a scene (a subset of its touches, new
provenance or sensor model).
Command line: ``tacsplat import blender|colmap|nerfstudio`` and ``tacsplat inspect DIR [--json] [--plot PNG]``.
"""

from .copying import copy_scene
from .reader import Scene, check_scene
from .records import SPLITS, Frame, HandMotion, SceneMeta, SensorModel, Touch
from .writer import SceneWriter

__all__ = [
    "SPLITS",
    "Frame",
    "Touch",
    "HandMotion",
    "SensorModel",
    "SceneMeta",
    "Scene",
    "check_scene",
    "SceneWriter",
    "copy_scene",
]

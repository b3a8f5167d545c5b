"""tacsplat.sim: the MuJoCo twin of the rig (see DESIGN.md).

Modules: ``hand`` (the Allegro-style hand MJCF and ``HandKinematics``; no MuJoCo
import at module level), ``objects`` (glossy procedural library, user meshes,
CoACD collision pieces), ``tactile`` (ray-cast indentation maps, synthetic
tactile RGB), ``camera`` (OpenCV-convention MuJoCo cameras), ``twin``
(``SimTwin`` implementing Hand, TactileSensor and Camera, plus the
simulator-only operations acquisition uses, such as ``reset``), ``views`` (hemisphere
camera poses), ``grasps`` (approach, preshape and tap target of a grasp; the
grasp controller itself is the acquisition logger's, and the jobs that grasp,
sim-capture and simulate-touches, are in tacsplat.acquisition).
MuJoCo's offscreen backend (``MUJOCO_GL``) defaults to EGL, set in ``tacsplat/__init__.py``.
"""

# The bounding-sphere radii (m) the twin's hand grasps (here, not in .objects: the CLI's help states it without
# importing trimesh). Measured on the six library objects, 8 grasps each: from 0.025 m most grasps touch the object
# with two or more pads (73 %, as at 0.03-0.04 m: 77-81 %); at 0.02 m fewer than half do (42 %), below 0.01 m one
# pad at most; below 0.003 m no grasp touches it, and at 0.0005 m MuJoCo refuses the object's inertia. 0.3 m:
# larger than the hand (about 0.2 m across); grasps still touch it.
OBJECT_RADIUS_RANGE_M = (0.025, 0.3)

# The near plane of the twin's cameras (m): MuJoCo draws nothing nearer, so a view camera must keep the object
# farther than this (acquisition.config checks plan.views.radius_m against it without importing MuJoCo).
VIEW_ZNEAR_M = 0.01

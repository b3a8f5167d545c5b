"""tacsplat.sim: the MuJoCo twin of the rig (see DESIGN.md).

Modules: ``hand`` (the Allegro-style hand MJCF and ``HandKinematics``; no MuJoCo
import at module level), ``objects`` (glossy procedural library, user meshes,
CoACD collision pieces), ``tactile`` (ray-cast indentation maps, synthetic
tactile RGB), ``camera`` (OpenCV-convention MuJoCo cameras), ``twin``
(``SimTwin`` implementing Hand, TactileSensor and Camera), ``views``,
``grasps``, ``capture`` (simulate-touches; sim-capture runs through tacsplat.acquisition) and ``bench``.
"""

import ctypes.util as _ctypes_util
import os as _os

# Offscreen rendering: EGL where its library exists, else OSMesa (set before MuJoCo is imported).
if "MUJOCO_GL" not in _os.environ:
    _os.environ["MUJOCO_GL"] = "egl" if _ctypes_util.find_library("EGL") else "osmesa"

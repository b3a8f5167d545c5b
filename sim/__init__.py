"""tacsplat.sim: the MuJoCo twin of the rig (see DESIGN.md).

Modules: ``hand`` (the Allegro-style hand MJCF and ``HandKinematics``; no MuJoCo
import at module level), ``objects`` (glossy procedural library, user meshes,
CoACD collision pieces), ``tactile`` (ray-cast indentation maps, synthetic
tactile RGB), ``camera`` (OpenCV-convention MuJoCo cameras), ``twin``
(``SimTwin`` implementing Hand, TactileSensor and Camera), ``views``,
``grasps``, ``capture`` (simulate-touches; sim-capture runs through tacsplat.acquisition).
MuJoCo's offscreen backend (``MUJOCO_GL``) defaults to EGL, set in ``tacsplat/__init__.py``.
"""

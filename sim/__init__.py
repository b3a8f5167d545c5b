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

"""tacsplat.acquisition: capture plans, the logger, the operator session and the simulated capture.

* :mod:`~tacsplat.acquisition.config`: the rig YAML (devices, calibration
  files, mounting transforms, board, grasp control, capture plan) as
  dataclasses, :func:`load_rig`; examples in ``acquisition/rigs/``;
* :mod:`~tacsplat.acquisition.devices`: :func:`open_rig` turns a config into
  a :class:`Rig` (Hand, TactileSensors, Camera, clock, pose source) for the real
  rig, its ``--mock`` emulation (:mod:`~tacsplat.acquisition.mock`) or the twin;
* :mod:`~tacsplat.acquisition.logger`: :class:`CaptureLogger`, the one code
  path that writes views and grasps through ``SceneWriter``;
* :mod:`~tacsplat.acquisition.session`: ``tacsplat capture``, the operator's
  terminal session (:func:`run_capture`);
* :mod:`~tacsplat.acquisition.sim_capture`: the unattended capture on the twin
  (``tacsplat sim-capture``), through the same logger.
"""

from tacsplat.acquisition.config import RigConfig, load_rig
from tacsplat.acquisition.logger import CaptureLogger, CaptureRejected

__all__ = ["RigConfig", "load_rig", "CaptureLogger", "CaptureRejected"]

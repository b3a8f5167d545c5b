"""tacsplat.acquisition: capture plans, the logger, and the three jobs that write scenes through it.

* :mod:`~tacsplat.acquisition.config`: the rig YAML (devices, calibration
  files, mounting transforms, board, grasp control, capture plan) as
  dataclasses, :func:`load_rig`; examples in ``acquisition/rigs/``;
* :mod:`~tacsplat.acquisition.devices`: :func:`open_rig` turns a config into
  a :class:`Rig` (Hand, TactileSensors, Camera, clock, pose source) for the real
  rig, its ``--mock`` emulation (:mod:`~tacsplat.acquisition.mock`) or the twin;
* :mod:`~tacsplat.acquisition.logger`: :class:`CaptureLogger`, the one code
  path that writes views and grasps through ``SceneWriter``, and the one grasp
  controller (close until the fingers stall, read, open);
* :mod:`~tacsplat.acquisition.capture_scene`: the scene a capture opens, and
  the checks of ``--resume``;
* :mod:`~tacsplat.acquisition.twin_planner`: places the twin's camera and hand
  for the logger, retrying an approach that touched nothing;
* :mod:`~tacsplat.acquisition.operator_session`: ``tacsplat capture``, the
  operator's terminal session (:func:`run_capture`);
* :mod:`~tacsplat.acquisition.sim_capture`: ``tacsplat sim-capture``, a whole
  scene captured on the twin, unattended;
* :mod:`~tacsplat.acquisition.touch_simulation`: ``tacsplat simulate-touches``,
  simulated grasps added to an existing scene;
* :mod:`~tacsplat.acquisition.paper_touches`: ``--touch-model paper`` of both,
  the touches of the paper's official code, recorded as pad touches.

Import from the modules themselves: the package imports nothing, so that
``tacsplat --help`` loads no rig configuration.
"""

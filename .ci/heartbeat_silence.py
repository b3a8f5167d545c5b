"""The longest silence on the hand's bus: the time between two instruction packets the driver sends while torque
is on, over N mock captures (3 views, 1 test view, 3 grasps each), beside the heartbeat's period (an eighth of
the Bus Watchdog's, ``bus_watchdog_s``): what a silence has beyond that period is the host's delay, which the
watchdog must outlast. Run it beside other work to see a loaded host.

    MUJOCO_GL=egl .venv/bin/python .ci/heartbeat_silence.py [N]
"""

import io
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "acquisition"))
from acq_helpers import ScriptedKeys, write_mock_rig  # noqa: E402

import tacsplat.drivers.dynamixel_hand as dynamixel_hand  # noqa: E402
from tacsplat.acquisition.config import load_rig  # noqa: E402
from tacsplat.acquisition.operator_session import run_capture  # noqa: E402

silences: list[float] = []
last: list[float | None] = [None]
period = [0.0]
enter = dynamixel_hand._Exchange.__enter__


def timed_enter(self):
    result = enter(self)
    now = time.monotonic()
    if last[0] is not None and self.hand._torque_on:
        silences.append(now - last[0])
        period[0] = self.hand.config.heartbeat_s
    last[0] = now
    return result


dynamixel_hand._Exchange.__enter__ = timed_enter
for i in range(int(sys.argv[1]) if len(sys.argv) > 1 else 3):
    folder = Path(tempfile.mkdtemp())
    last[0] = None
    code = run_capture(
        load_rig(write_mock_rig(folder), mock=True),
        folder / "scene",
        keys=ScriptedKeys("\n\n\nggg\n"),
        output=io.StringIO(),
    )
    ordered = sorted(silences)
    print(
        f"capture {i}: exit {code}; {len(ordered)} exchanges so far: median {statistics.median(ordered):.3f} s, "
        f"p99 {ordered[int(0.99 * len(ordered))]:.3f} s, longest {ordered[-1]:.3f} s (heartbeat every {period[0]:.3f} s)",
        flush=True,
    )

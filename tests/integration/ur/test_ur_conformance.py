"""The conformance kit (cellcal.testing) against the ``ur`` backend, through ur_rtde, on the UR emulator.

Each rule is one test. Most rules connect and close: ur_rtde sleeps 0.5 s in each
interface's ``disconnect()``, so this module takes about a second per rule.
"""

from __future__ import annotations

from collections.abc import Callable

import pytest

from cellcal.devices.arm import RobotArm
from cellcal.drivers.ur.arm import URArm
from cellcal.sims.ur.process import UREmulatorProcess
from cellcal.testing import ArmConformance, ArmOptions

pytest.importorskip("rtde_control")  # the ur extra


@pytest.mark.slow
class TestURArmOnTheEmulator(ArmConformance):
    options = ArmOptions(joint_count=6)

    @pytest.fixture
    def arm_factory(self, emu: UREmulatorProcess) -> Callable[[], RobotArm]:
        emu.call("set_time_scale", time_scale=0.02)  # the kit's 2 cm round trip at 0.05 m/s: ~20 ms
        return lambda: URArm.from_config({"host": emu.host, "poll_interval_s": 0.005})

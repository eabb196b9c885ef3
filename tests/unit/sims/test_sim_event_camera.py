"""``[[sim.events]]`` naming a camera (issue #40): a knocked camera of ``[[cameras]]``, the others untouched."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from cellcal.devices.base import BackendContext, CameraPlacement
from cellcal.devices.errors import ConfigError
from cellcal.devices.pose import Pose
from cellcal.sims.camera import SimCamera, SimCameraConfig
from cellcal.sims.work import EventConfig

MOUNT = {"translation_m": [0.0, 0.04, 0.06], "rpy_deg": [0.0, 0.0, 90.0]}
ABOVE = Pose.from_xyz_rpy([0.3, 0.0, 1.2], np.radians([180.0, 0.0, 0.0]))
#: 'above' knocked at 2 s: 0.5 deg more roll, 1 mm lower (its new true T_base_camera).
KNOCK = {"at_s": 2.0, "camera": "above", "mount_translation_m": [0.3, 0.0, 1.199], "mount_rpy_deg": [180.5, 0.0, 0.0]}


def _cell(events: list[dict[str, Any]]) -> tuple[SimCamera, SimCamera, SimCamera]:
    """The driven camera, 'above' (fixed) and 'hand' (a second camera on the flange) in one world, connected."""
    doc = {"mount": MOUNT, "sim": {"events": events}}
    shared: dict[str, Any] = {}
    names = ("wrist", "above", "hand")

    def camera(section: str, placement: CameraPlacement | None) -> SimCamera:
        return SimCamera(SimCameraConfig(), BackendContext(document=doc, shared=shared, seed=1, section=section,
                                                            placement=placement, camera_names=names))

    driven = camera("camera", None)
    above = camera("cameras[1]", CameraPlacement("above", "base", ABOVE))
    hand = camera("cameras[2]", CameraPlacement("hand", "flange", Pose.from_xyz_rpy([0.0, -0.04, 0.06], [0, 0, 0])))
    for c in (driven, above, hand):
        c.connect()
    return driven, above, hand


def test_an_event_naming_a_fixed_camera_moves_it_alone_when_its_time_comes() -> None:
    driven, above, hand = _cell([KNOCK])
    before = (driven.camera_pose(), above.camera_pose(), hand.camera_pose())
    assert above.camera_pose().is_close(ABOVE, atol_m=1e-12, atol_rad=1e-12)
    driven.world.clock.advance_to(2.5)
    after = (driven.camera_pose(), above.camera_pose(), hand.camera_pose())
    # 'above' turned 0.5 deg and 1 mm lower; the cameras on the flange where they were (the arm at rest)
    assert np.degrees(before[1].angle_to(after[1])) == pytest.approx(0.5, abs=1e-9)
    assert after[1].translation[2] == pytest.approx(1.199, abs=1e-12)
    assert after[0].is_close(before[0], atol_m=1e-12, atol_rad=1e-12)
    assert after[2].is_close(before[2], atol_m=1e-12, atol_rad=1e-12)


def test_an_event_naming_the_driven_camera_or_none_moves_the_driven_one() -> None:
    for named in ({"camera": "wrist"}, {}):
        event = {"at_s": 1.0, "mount_translation_m": [0.0, 0.04, 0.061], "mount_rpy_deg": [0.0, 0.0, 90.0], **named}
        driven, above, _ = _cell([event])
        driven.world.clock.advance_to(1.5)
        driven.camera_pose()                                  # the events whose time has come are applied
        assert driven.world.mount.translation[2] == pytest.approx(0.061, abs=1e-12)
        assert above.camera_pose().is_close(ABOVE, atol_m=1e-12, atol_rad=1e-12)


def test_an_event_naming_no_camera_of_the_cell_or_changing_nothing_is_refused() -> None:
    with pytest.raises(ConfigError, match=r"'ceiling' names no camera of the cell \(its cameras: wrist, above, hand\)"):
        _cell([{**KNOCK, "camera": "ceiling"}])
    with pytest.raises(ConfigError, match="camera names whose pose changes"):
        EventConfig(at_s=1.0, camera="above", plane_point_m=(0.0, 0.0, 0.0), plane_normal=(0.0, 0.0, 1.0))

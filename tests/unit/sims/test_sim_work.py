"""``[sim.work]`` and ``[[sim.events]]``: the simulated arm's own program and the accidents of a cell."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest

from cellcal.devices.base import BackendContext
from cellcal.devices.config import parse_section
from cellcal.devices.errors import ConfigError
from cellcal.devices.pose import Pose
from cellcal.sims.motion import trapezoid_duration
from cellcal.sims.work import WorkConfig, WorkPlan
from cellcal.sims.world import world_from_context

A = [0.30, 0.10, 0.50]
B = [0.30, -0.10, 0.50]
START = Pose.from_xyz_rpy(np.array([0.30, 0.0, 0.50]), np.radians([180.0, 0.0, 0.0]))


def _plan(dwell_s: float = 1.0) -> WorkPlan:
    config = parse_section(WorkConfig, {"poses": [{"translation_m": A}, {"translation_m": B}], "speed_m_s": 0.1,
                                        "acceleration_m_s2": 0.5, "dwell_s": dwell_s}, where="sim.work")
    return WorkPlan(START, config)


def test_the_work_moves_dwells_and_repeats_on_the_simulated_clock() -> None:
    plan = _plan()
    lead = trapezoid_duration(0.10, 0.1, 0.5)              # start -> A: 0.1 m at 0.1 m/s, 0.5 m/s^2
    leg = trapezoid_duration(0.20, 0.1, 0.5)               # A -> B and back
    assert (lead, leg) == pytest.approx((1.2, 2.2))
    assert plan.cycle_s == pytest.approx(2 * leg + 2 * 1.0)
    np.testing.assert_allclose(plan.pose_at(0.0).translation, START.translation)
    np.testing.assert_allclose(plan.pose_at(lead + 0.5).translation, A)          # dwelling at A
    np.testing.assert_allclose(plan.pose_at(lead + 1.0 + leg / 2).translation, [0.30, 0.0, 0.50], atol=1e-12)
    np.testing.assert_allclose(plan.pose_at(lead + 1.0 + leg + 0.5).translation, B)  # dwelling at B
    for t in (lead + 0.3, lead + 1.7, lead + 3.9):                             # one cycle later: the same pose
        np.testing.assert_allclose(plan.pose_at(t + plan.cycle_s).translation, plan.pose_at(t).translation,
                                   atol=1e-12)
        np.testing.assert_allclose(plan.pose_at(t + 7 * plan.cycle_s).translation, plan.pose_at(t).translation,
                                   atol=1e-12)


def _world(sim: dict[str, Any]) -> Any:
    doc = {"sim": sim, "mount": {"translation_m": [0.0, 0.04, 0.06], "rpy_deg": [0.0, 0.0, 90.0]}}
    return world_from_context(BackendContext(document=doc))


def test_the_arm_follows_its_work_and_the_truth_changes_at_the_events() -> None:
    world = _world({"initial_flange_translation_m": [0.30, 0.0, 0.50],
                    "work": {"poses": [{"translation_m": A}, {"translation_m": B}], "dwell_s": 1.0},
                    "events": [{"at_s": 3.0, "mount_translation_m": [0.0, 0.04, 0.06], "mount_rpy_deg": [0.5, 0, 90]},
                               {"at_s": 5.0, "plane_point_m": [0.0, 0.0, 0.005], "plane_normal": [0, 0, 1]}]})
    assert world.arm.working
    world.clock.advance_to(1.7)
    world.camera_pose()
    np.testing.assert_allclose(world.arm.flange_pose().translation, A)
    assert math.degrees(world.mount.angle_to(Pose.from_xyz_rpy(np.array([0, 0.04, 0.06]),
                                                               np.radians([0, 0, 90])))) == pytest.approx(0, abs=1e-9)
    world.clock.advance_to(3.0)
    world.camera_pose()                                     # the knock: 0.5 deg of roll
    knocked = Pose.from_xyz_rpy(np.array([0, 0.04, 0.06]), np.radians([0.5, 0, 90]))
    assert world.mount.angle_to(knocked) < 1e-12 and world.scene.plane_point_m[2] == 0.0
    world.clock.advance_to(5.0)
    world.camera_pose()                                     # the table: 5 mm up
    assert world.scene.plane_point_m.tolist() == [0.0, 0.0, 0.005] and world.events == []


def test_a_commanded_motion_ends_the_work() -> None:
    from cellcal.sims.motion import LinearMotion

    world = _world({"work": {"poses": [{"translation_m": A}]}})
    here = world.arm.flange_pose()
    world.arm.start_motion(LinearMotion(here, here, 0.1, 0.5), 0.0)
    assert not world.arm.working


@pytest.mark.parametrize(("sim", "says"), [
    ({"work": {}}, "poses"),
    ({"work": {"poses": []}}, "needs at least 1 items"),
    ({"work": {"poses": [{"translation_m": A}], "speed": 1}}, "speed"),
    ({"work": {"poses": [{"translation_m": A}], "speed_m_s": 2.0}}, "speed_m_s"),
    ({"events": [{"at_s": 1.0}]}, "changes nothing"),
    ({"events": [{"at_s": 1.0, "mount_rpy_deg": [0, 0, 0]}]}, "needs both mount_translation_m and mount_rpy_deg"),
    ({"events": [{"at_s": 1.0, "plane_point_m": [0, 0, 0]}]}, "needs both plane_point_m and plane_normal"),
    ({"events": [{"at_s": 1.0, "plane_point_m": [0, 0, 0], "plane_normal": [0, 0, 0]}]}, "non-zero"),
    ({"events": [{"at_s": -1.0, "plane_point_m": [0, 0, 0], "plane_normal": [0, 0, 1]}]}, "at_s"),
])
def test_a_bad_work_or_event_table_is_one_clear_error(sim: dict[str, Any], says: str) -> None:
    with pytest.raises(ConfigError, match=says) as info:
        _world(sim)
    assert "\n" not in str(info.value)

"""The calibration workflow: cell config, calibrator, journal, output lock, dry run, report.

The ``replay`` names (the MCAP recording's reader and writer) are imported on first use
(PEP 562), so ``cellcal calibrate`` does not load the recording stack (ADR 0021).
"""

from typing import TYPE_CHECKING

from cellcal.core.calibration.build import build_camera, build_cell, build_devices
from cellcal.core.calibration.calibrator import (
    Calibrator,
    poses_saved,
    run_to_file,
)
from cellcal.core.calibration.config import (
    CellConfig,
    load_config,
    load_every_camera,
    look_at_pose,
    parse_config,
    plan_flange_poses,
    read_config_text,
)
from cellcal.core.calibration.dryrun import (
    MoveCheck,
    check_moves,
    describe,
    dry_run,
)
from cellcal.core.calibration.journal import (
    JOURNAL_SCHEMA,
    JOURNAL_SUFFIX,
    JournalEntry,
    JournalWriter,
    journal_path,
    plan_fingerprint,
    read_journal,
    remove_journal,
)
from cellcal.core.calibration.outlock import LOCK_NAME, OutputLock
from cellcal.core.calibration.record import PoseRecord
from cellcal.core.calibration.report import (
    format_full_frame,
    format_table,
    plane_summary,
    summarize,
    summarize_poses,
    write_bytes_atomic,
    write_json_atomic,
)
from cellcal.core.calibration.sections import (
    CellSection,
    MonitorSection,
    MountSection,
    PlanPose,
    PlanSection,
    ReferenceSection,
    RegionSection,
    SafetySection,
)
from cellcal.devices.lazy import lazy_exports

__all__ = [
    "JOURNAL_SCHEMA",
    "JOURNAL_SUFFIX",
    "LOCK_NAME",
    "Calibrator",
    "CellConfig",
    "CellSection",
    "JournalEntry",
    "JournalWriter",
    "MonitorSection",
    "MountSection",
    "MoveCheck",
    "OutputLock",
    "PlanPose",
    "PlanSection",
    "PoseRecord",
    "ReferenceSection",
    "RegionSection",
    "SafetySection",
    "build_camera",
    "build_cell",
    "build_devices",
    "check_moves",
    "compare_with_recording",
    "describe",
    "dry_run",
    "exact_part",
    "format_full_frame",
    "format_table",
    "journal_path",
    "load_config",
    "load_every_camera",
    "look_at_pose",
    "parse_config",
    "plan_fingerprint",
    "plan_flange_poses",
    "plane_summary",
    "poses_saved",
    "read_config_text",
    "read_journal",
    "record",
    "remove_journal",
    "replay_session",
    "run_recorded",
    "run_to_file",
    "summarize",
    "summarize_poses",
    "write_bytes_atomic",
    "write_json_atomic",
]

#: Names of :mod:`cellcal.core.calibration.replay`, imported on first use.
_REPLAY = {name: ".replay" for name in ("compare_with_recording", "exact_part", "record", "replay_session",
                                         "run_recorded")}

if TYPE_CHECKING:
    from cellcal.core.calibration.replay import (
        compare_with_recording,
        exact_part,
        record,
        replay_session,
        run_recorded,
    )


__getattr__, __dir__ = lazy_exports(__name__, _REPLAY)

"""Several cameras on the flange in one ``cellcal handeye`` run (issue #40, ADR 0061).

The driven camera's plan is run as for one camera; every other camera of ``[[cameras]]`` with
``on = "flange"`` captures at each pose beside it (:class:`~cellcal.core.calibration.cell_capture.OtherCameras`:
together where its ``capture`` allows, else after), and its full-frame planes, seen from
``reported flange @ its mount``, go through the same estimator as the driven camera's
(:func:`~cellcal.core.handeye.run.estimate_from_document` with its own configured mount as the start),
written to ``DIR/handeye-NAME.json`` (the schema of ``handeye.json``, its camera named). A camera whose
poses cannot support a mount (too few planes, a parameter unobservable, residuals far beyond the
noise) gets a line saying why and no file. Fixed cameras are not part of the run: each has
``cellcal handeye --camera NAME`` (the plate).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from cellcal.core.calibration.cell_capture import OtherCameras
from cellcal.core.calibration.config import CellConfig
from cellcal.core.calibration.report import write_json_atomic
from cellcal.core.handeye.run import estimate_from_document, handeye_result
from cellcal.devices.arm_model import ArmModel
from cellcal.devices.camera import Camera3D
from cellcal.devices.errors import CalibrationError
from cellcal.devices.pose import Pose

__all__ = ["MIN_FITTED_POSES", "FlangeCameras", "FlangeOutcome", "flange_handeye_filename", "split_cell_cameras"]

#: Fewest poses with a fitted plane a mount is estimated from (9 parameters, 3 constraints per plane).
MIN_FITTED_POSES = 3


def flange_handeye_filename(name: str) -> str:
    """The hand-eye result of camera ``name`` (on the flange, not the driven one) beside ``handeye.json``."""
    return f"handeye-{name}.json"


def split_cell_cameras(config: CellConfig, cameras: Mapping[str, Camera3D]
                       ) -> tuple[dict[str, Camera3D], list[str]]:
    """The other cameras on the flange (captured in the run) and the fixed cameras' names (left out).

    Args:
        config: The cell (its ``cameras`` say where each is).
        cameras: The cell's cameras other than the driven one, by name.
    """
    places = {e.name: e.on for e in config.cameras}
    flange = {name: cam for name, cam in cameras.items() if places[name] == "flange"}
    return flange, [name for name in cameras if places[name] != "flange"]


@dataclass(frozen=True)
class FlangeOutcome:
    """What one other camera on the flange got from the run.

    Attributes:
        name: The camera.
        path: Its ``handeye-NAME.json`` (None: no mount).
        document: What was written (None: no mount).
        problem: Why there is no mount ("" when there is one).
        fitted: Poses with a fitted plane, of ``poses`` captured.
    """

    name: str
    path: Path | None
    document: dict[str, Any] | None
    problem: str
    fitted: int
    poses: int

    def line(self) -> str:
        """One line for the terminal: the mount and its 95 % half-widths, or why none."""
        if self.document is None:
            return f"camera {self.name!r} (on the flange): no mount: {self.problem}"
        mount = self.document["mount"]
        t = " ".join(f"{1000 * v:+.2f}±{1000 * (hi - lo) / 2:.2f}"
                     for v, (lo, hi) in zip(mount["translation_m"], mount["translation_ci_m"], strict=True))
        r = " ".join(f"{v:+.3f}±{(hi - lo) / 2:.3f}"
                     for v, (lo, hi) in zip(mount["rpy_deg"], mount["rpy_ci_deg"], strict=True))
        return (f"camera {self.name!r} (on the flange): mount xyz {t} mm, rpy {r} deg from {self.fitted} of "
                f"{self.poses} poses; written to {self.path}")


class FlangeCameras(OtherCameras):
    """The other cameras on the flange of a ``handeye`` run: captured at each pose, each estimated after it."""

    def __init__(self, config: CellConfig, cameras: Mapping[str, Camera3D]) -> None:
        super().__init__(config, cameras)
        #: One per camera after :meth:`estimate_and_write`, in the configuration's order.
        self.outcomes: list[FlangeOutcome] = []

    def estimate_and_write(self, config: CellConfig, arm_model: ArmModel | None, out_dir: Path,
                           header: Mapping[str, Any]) -> list[FlangeOutcome]:
        """Estimate each camera's mount from its own poses' planes; write ``DIR/handeye-NAME.json`` atomically.

        Args:
            config: The driven camera's configuration (``[handeye]``, ``[reference]``).
            arm_model: The arm's stated accuracy (as for the driven camera).
            out_dir: The run's directory.
            header: The driven camera's ``handeye.json`` header; ``camera`` is replaced by each camera's name.

        Returns:
            :attr:`outcomes`.
        """
        self.outcomes = [self._one(config, name, arm_model, out_dir, header) for name in self.cameras]
        return self.outcomes

    def _one(self, config: CellConfig, name: str, arm_model: ArmModel | None, out_dir: Path,
             header: Mapping[str, Any]) -> FlangeOutcome:
        entries = self.poses[name]
        fitted = [e for e in entries if "full_frame" in e]
        if len(fitted) < MIN_FITTED_POSES:
            why = "; ".join(sorted({e.get("error", "") for e in entries if "error" in e}))[:200]
            return FlangeOutcome(name, None, None, f"a plane at {len(fitted)} of {len(entries)} poses, at least "
                                 f"{MIN_FITTED_POSES} needed" + (f" ({why})" if why else ""), len(fitted), len(entries))
        _on, nominal = self.places[name]
        try:
            estimate = estimate_from_document(config, {"poses": fitted}, arm_model, mount=nominal)
        except CalibrationError as exc:  # unobservable, or residuals far beyond the noise: said, not raised
            return FlangeOutcome(name, None, None, str(exc), len(fitted), len(entries))
        flanges = [Pose.from_dict(e["reported_flange_pose"]) for e in fitted]
        head = {**header, "camera": name, "driven_camera": config.camera_name, "capture": self.capture_document(),
                "plan_poses_used": [int(e["index"]) for e in fitted],
                "failed_poses": [int(e["index"]) for e in entries if "error" in e]}
        document = handeye_result(config, estimate, flanges, nominal, head)
        path = write_json_atomic(Path(out_dir) / flange_handeye_filename(name), document)
        return FlangeOutcome(name, path, document, "", len(fitted), len(entries))

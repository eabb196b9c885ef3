"""Cell configuration: a TOML document validated into typed objects (ADR 0004).

Tables: ``[cell]``, ``[camera]``/``[arm]`` (``backend = "name"``, the rest validated by
the backend) or ``[[cameras]]`` (several cameras: :mod:`cellcal.core.calibration.cameras`), ``[mount]``,
``[reference]``, ``[region]``, ``[safety]``, ``[plan]``, ``[monitor]``,
``[full_frame]`` and ``[sim]``; see ``configs/sim.toml``. This module reads the file and the
document as a whole into a :class:`CellConfig` and generates the plan's poses; each table's
dataclass is in :mod:`cellcal.core.calibration.sections`. Any problem raises
:class:`~cellcal.devices.errors.ConfigError` naming the file, the dotted key and the expectation.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import os
import stat
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from cellcal.core.calibration.cameras import (
    CameraEntry,
    PlateSection,
    parse_cameras,
    select_camera,
    single_camera_document,
)
from cellcal.core.calibration.sections import (
    CellSection,
    DepthcalSection,
    HandEyeSection,
    MonitorSection,
    MountSection,
    PlanSection,
    ReferenceSection,
    RegionSection,
    SafetySection,
)
from cellcal.core.methods.fullframe import FullFrameSettings
from cellcal.devices import boundedjson
from cellcal.devices.config import parse_section
from cellcal.devices.errors import ConfigError
from cellcal.devices.pose import Pose
from cellcal.devices.safety import SafetyLimits

TOP_LEVEL_TABLES = ("cell", "camera", "cameras", "arm", "mount", "reference", "region", "safety", "plan", "sim",
                    "monitor", "full_frame", "handeye", "depthcal", "plate")
#: Backends built on the simulated world, the only readers of ``[sim]`` (tests/unit/core/calibration/test_config.py
#: checks this against the registered backends that live in ``cellcal.sims``).
SIM_BACKENDS = frozenset({"sim", "o3r-emulated", "xarm-emulated", "ur-emulated"})

log = logging.getLogger(__name__)
DEFAULT_CONFIG_NAME = "sim.toml"
#: Largest configuration file read, bytes (a cell's configuration is a few KB).
MAX_CONFIG_BYTES = 1 << 20


@dataclass(frozen=True)
class CellConfig:
    """A validated cell configuration.

    Attributes:
        source: Where it was read from (file path or ``"<packaged sim.toml>"``).
        document: The raw TOML document (backends validate their own sections).
    """

    source: str
    document: Mapping[str, Any]
    cell: CellSection
    mount: MountSection
    reference: ReferenceSection | None
    safety: SafetySection
    plan: PlanSection
    monitor: MonitorSection = field(default_factory=MonitorSection)
    full_frame: FullFrameSettings = field(default_factory=FullFrameSettings)
    handeye: HandEyeSection = field(default_factory=HandEyeSection)
    region: RegionSection = field(default_factory=RegionSection)
    depthcal: DepthcalSection = field(default_factory=DepthcalSection)
    #: Every camera of the cell (``[[cameras]]``, or the one ``[camera]``); ``document`` holds the one this
    #: configuration runs (:attr:`camera_name`) as ``[camera]`` and ``[mount]``.
    cameras: tuple[CameraEntry, ...] = ()
    camera_name: str = "camera"
    #: Where the running camera's table is in the file, for messages: ``camera``, or ``cameras[i]``.
    camera_key: str = "camera"
    plate: PlateSection = field(default_factory=PlateSection)

    @property
    def camera_entry(self) -> CameraEntry:
        """The camera this configuration runs (:attr:`camera_name`) among :attr:`cameras`."""
        return next(c for c in self.cameras if c.name == self.camera_name)

    @property
    def search_reference(self) -> ReferenceSection | None:
        """The ``[reference]`` the fit searches near, or None: no reference, ``search = false`` or no ``[mount]``.

        Without a ``[mount]`` table the mount is the identity, which says nothing about where
        the camera looks, so the plane it predicts cannot restrict the fit.
        """
        ref = self.reference
        return ref if ref is not None and ref.search and "mount" in self.document else None

    @property
    def camera_section(self) -> Mapping[str, Any]:
        """The ``[camera]`` table (with ``backend``)."""
        return self.document["camera"]  # type: ignore[no-any-return]

    @property
    def arm_section(self) -> Mapping[str, Any]:
        """The ``[arm]`` table (with ``backend``)."""
        return self.document["arm"]  # type: ignore[no-any-return]

    def safety_limits(self) -> SafetyLimits:
        """The envelope, with the reference plane for the standoff check when known."""
        ref = self.reference
        return SafetyLimits(
            workspace_min_m=self.safety.workspace_min_m,
            workspace_max_m=self.safety.workspace_max_m,
            max_speed_m_s=self.safety.max_speed_m_s,
            max_acceleration_m_s2=self.safety.max_acceleration_m_s2,
            min_standoff_m=self.safety.min_standoff_m,
            plane_point_m=ref.plane_point_m if ref else None,
            plane_normal=ref.plane_normal if ref else None,
            mount=self.mount.pose(),
            arrival_tolerance_m=self.safety.arrival_tolerance_m,
            arrival_tolerance_rad=None if self.safety.arrival_tolerance_deg is None
            else math.radians(self.safety.arrival_tolerance_deg),
        )


def parse_config(document: Mapping[str, Any], source: str, camera: str | None = None,
                 allow_fixed: bool = False) -> CellConfig:
    """Validate a parsed TOML document.

    A ``[sim]`` table next to backends that are all real is logged as a one-line warning
    (logger ``cellcal.core.calibration.config``): it is valid but has no effect.

    Args:
        document: The parsed TOML.
        source: Where it came from, for messages.
        camera: With ``[[cameras]]``: the camera the configuration runs (None: the first on the flange).
        allow_fixed: ``camera`` may be a fixed camera (``on = "base"``: ``cellcal handeye`` runs one).

    Raises:
        ConfigError: Naming ``source``, the key and the expectation.
    """
    for key, value in document.items():
        if key not in TOP_LEVEL_TABLES:
            raise ConfigError(f"unknown table; expected one of: {', '.join(TOP_LEVEL_TABLES)}", source=source, key=key)
        if not isinstance(value, Mapping) and key != "cameras":
            raise ConfigError(f"expected a table, got {type(value).__name__}", source=source, key=key)
    cameras, chosen, camera_key, document = _running_camera(document, source, camera, allow_fixed)
    for required in ("camera", "arm"):
        if required not in document:
            raise ConfigError("missing table (it needs at least backend = \"...\")", source=source, key=required)
        if not isinstance(document[required].get("backend"), str):
            raise ConfigError("missing or non-string 'backend'", source=source, key=f"{required}.backend")
    if "sim" in document and not {document["camera"]["backend"], document["arm"]["backend"]} & SIM_BACKENDS:
        log.warning("%s: [sim] has no effect: camera backend %r and arm backend %r are not simulated "
                    "(only %s read it)", source, document["camera"]["backend"], document["arm"]["backend"],
                    ", ".join(sorted(SIM_BACKENDS)))
    ref = document.get("reference")
    plan = parse_section(PlanSection, document.get("plan"), where="plan", source=source)
    if plan.inclination_deg < 90 and not plan.poses and ref is None:
        raise ConfigError("generated plan poses need a [reference] plane (or give explicit [[plan.poses]])",
                          source=source, key="reference")
    return CellConfig(
        source=source,
        document=document,
        cell=parse_section(CellSection, document.get("cell"), where="cell", source=source),
        mount=_mount_from_handeye(parse_section(MountSection, document.get("mount"), where="mount", source=source),
                                  document.get("mount"), source),
        reference=None if ref is None else parse_section(ReferenceSection, ref, where="reference", source=source),
        safety=parse_section(SafetySection, document.get("safety"), where="safety", source=source),
        plan=plan,
        monitor=parse_section(MonitorSection, document.get("monitor"), where="monitor", source=source),
        full_frame=parse_section(FullFrameSettings, document.get("full_frame"), where="full_frame", source=source),
        handeye=parse_section(HandEyeSection, document.get("handeye"), where="handeye", source=source),
        region=parse_section(RegionSection, document.get("region"), where="region", source=source),
        depthcal=parse_section(DepthcalSection, document.get("depthcal"), where="depthcal", source=source),
        cameras=cameras,
        camera_name=chosen.name,
        camera_key=camera_key,
        plate=parse_section(PlateSection, document.get("plate"), where="plate", source=source),
    )


def _running_camera(document: Mapping[str, Any], source: str, camera: str | None, allow_fixed: bool
                    ) -> tuple[tuple[CameraEntry, ...], CameraEntry, str, Mapping[str, Any]]:
    """The cell's cameras, the one to run, where its table is (``camera`` or ``cameras[i]``) and the document
    that holds it as ``[camera]`` and ``[mount]`` (:func:`~cellcal.core.calibration.cameras.single_camera_document`).

    Raises:
        ConfigError: As :func:`parse_cameras` and :func:`select_camera`; ``camera`` naming another than ``[camera]``.
    """
    cameras = parse_cameras(document, source)
    if "cameras" not in document:
        if camera is not None and camera != cameras[0].name:
            raise ConfigError(f"no camera named {camera!r}; the cell has one, {cameras[0].name!r} ([camera])",
                              source=source, key="camera")
        return cameras, cameras[0], "camera", document
    chosen = select_camera(cameras, camera, source, allow_fixed)
    return cameras, chosen, f"cameras[{cameras.index(chosen)}]", single_camera_document(document, chosen)


#: Schema prefix of the documents ``[mount] from_handeye`` reads (``cellcal handeye``'s output).
HANDEYE_SCHEMA_PREFIX = "cellcal.handeye/"
#: Every schema whose mount ``from_handeye`` takes: a hand-eye result, a tracked calibration (``track --apply``).
MOUNT_SCHEMA_PREFIXES = (HANDEYE_SCHEMA_PREFIX, "cellcal.track-calibration/")


def _mount_from_handeye(mount: MountSection, table: Mapping[str, Any] | None, source: str) -> MountSection:
    """``mount`` with the estimate of its ``from_handeye`` file in place of ``translation_m`` / ``rpy_deg``.

    Raises:
        ConfigError: If the file cannot be read, is not a hand-eye result, or the table also
            sets ``translation_m`` / ``rpy_deg``.
    """
    if mount.from_handeye is None:
        return mount
    key = "mount.from_handeye"
    if any(k in (table or {}) for k in ("translation_m", "rpy_deg")):
        raise ConfigError("give either from_handeye or translation_m / rpy_deg, not both", source=source, key=key)
    path = Path(mount.from_handeye).expanduser()
    if not path.is_absolute() and Path(source).is_file():
        path = Path(source).parent / path  # relative to the configuration file
    text, where = read_config_text(path)
    try:
        data = boundedjson.loads(text)
        estimate, schema = data["mount"], data["schema"]
        values = {"translation_m": estimate["translation_m"], "rpy_deg": estimate["rpy_deg"]}
    except (ValueError, KeyError, TypeError):
        raise ConfigError("not a handeye.json of 'cellcal handeye' nor a calibration.json of 'cellcal track --apply' "
                          "(no mount.translation_m / mount.rpy_deg)",
                          source=where) from None
    if not str(schema).startswith(MOUNT_SCHEMA_PREFIXES):
        raise ConfigError(f"schema {schema!r} is not {' or '.join(p + 'N' for p in MOUNT_SCHEMA_PREFIXES)}",
                          source=where)
    parsed = parse_section(MountSection, values, where="mount", source=where)
    return dataclasses.replace(parsed, from_handeye=mount.from_handeye)


def read_config_text(path: str | Path | None) -> tuple[str, str]:
    """The text of a configuration file and its source name; None reads the packaged ``sim.toml``.

    Only a regular file of at most :data:`MAX_CONFIG_BYTES` is read: a FIFO, a device or
    a directory is refused before any read (a FIFO would block, ``/dev/zero`` never end).

    Raises:
        ConfigError: If the file is missing, not a regular file, too large, unreadable or not UTF-8.
    """
    if path is None:
        text = resources.files("cellcal.configs").joinpath(DEFAULT_CONFIG_NAME).read_text(encoding="utf-8")
        return text, f"<packaged {DEFAULT_CONFIG_NAME}>"
    source = str(path)
    if not source:
        raise ConfigError("empty path; expected a configuration file (TOML)")
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC)  # O_NONBLOCK: a FIFO opens at once
    except FileNotFoundError:
        raise ConfigError("file not found", source=source) from None
    except (OSError, ValueError) as exc:  # ValueError: a NUL byte in the path
        raise ConfigError(f"cannot read: {getattr(exc, 'strerror', None) or exc}", source=source) from None
    try:
        kind = os.fstat(fd).st_mode
        if stat.S_ISDIR(kind):
            raise ConfigError("is a directory; expected a configuration file (TOML)", source=source)
        if not stat.S_ISREG(kind):
            raise ConfigError("not a regular file (a FIFO, device or socket is no configuration file)",
                              source=source)
        data = _read_at_most(fd, MAX_CONFIG_BYTES + 1)
    except OSError as exc:
        raise ConfigError(f"cannot read: {exc.strerror or exc}", source=source) from None
    finally:
        os.close(fd)
    if len(data) > MAX_CONFIG_BYTES:
        raise ConfigError(f"larger than {MAX_CONFIG_BYTES} bytes; not a cell configuration", source=source)
    try:
        return data.decode("utf-8"), source
    except UnicodeDecodeError as exc:
        raise ConfigError(f"not UTF-8 text: byte 0x{data[exc.start]:02x} at offset {exc.start}",
                          source=source) from None


def _read_at_most(fd: int, limit: int) -> bytes:
    """Up to ``limit`` bytes of the open file ``fd`` (fewer at its end)."""
    chunks: list[bytes] = []
    size = 0
    while size < limit:
        chunk = os.read(fd, limit - size)
        if not chunk:
            break
        chunks.append(chunk)
        size += len(chunk)
    return b"".join(chunks)


def load_config(path: str | Path | None = None, camera: str | None = None, allow_fixed: bool = False) -> CellConfig:
    """Read and validate a configuration file; None loads the packaged ``sim.toml``.

    ``camera`` picks one of ``[[cameras]]`` (a camera on the flange, or a fixed one with ``allow_fixed``;
    None: the first on the flange).

    Raises:
        ConfigError: If the file is missing, unreadable (:func:`read_config_text`), not
            valid TOML, or fails validation.
    """
    return parse_config(*_read_document(path), camera, allow_fixed)


def _read_document(path: str | Path | None) -> tuple[dict[str, Any], str]:
    """The parsed TOML of ``path`` (None: the packaged ``sim.toml``) and where it was read from."""
    text, source = read_config_text(path)
    try:
        return tomllib.loads(text), source
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"invalid TOML: {exc}", source=source) from None
    except RecursionError:  # tomllib parses nested arrays and inline tables recursively
        raise ConfigError("invalid TOML: arrays or inline tables nested too deeply", source=source) from None


def load_every_camera(path: str | Path | None = None) -> list[CellConfig]:
    """Read a configuration once and validate it for each of its cameras, in the file's order.

    One ``[camera]`` gives one configuration; ``[[cameras]]`` one per camera, on the flange or fixed
    (each as :func:`load_config` with that camera and ``allow_fixed``).

    Raises:
        ConfigError: As :func:`load_config`.
    """
    document, source = _read_document(path)
    if "cameras" not in document:
        return [parse_config(document, source)]
    return [parse_config(document, source, c.name, allow_fixed=True) for c in parse_cameras(document, source)]


def look_at_pose(target_m: np.ndarray, normal: np.ndarray, height_m: float, inclination_rad: float,
                 tilt_axis: str) -> Pose:
    """Camera pose (base frame) whose optical axis hits ``target_m`` at ``height_m``.

    The untilted camera looks straight down the plane normal with its x axis along the
    base x axis as far as possible; it is then rotated about its own ``tilt_axis`` by
    ``pi/2 - inclination_rad`` about the target point.
    """
    n = normal / np.linalg.norm(normal)
    z = -n
    ref = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = ref - (ref @ z) * z
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    r_down = Pose.from_rotation_matrix(np.column_stack([x, y, z]))
    tilt = math.pi / 2 - inclination_rad
    r = r_down @ Pose.from_xyz_rotvec(np.zeros(3), (tilt if tilt_axis == "x" else 0.0,
                                                    tilt if tilt_axis == "y" else 0.0, 0.0))
    optical_axis = r.apply_vector([0.0, 0.0, 1.0])
    return Pose.from_rotation_matrix(r.rotation_matrix, target_m - height_m * optical_axis)


def plan_flange_poses(config: CellConfig) -> list[Pose]:
    """The flange poses (base frame) of the plan, in order."""
    plan = config.plan
    if plan.poses:
        return [p.pose() for p in plan.poses]
    assert config.reference is not None  # checked in parse_config
    mount_inv = config.mount.pose().inv()
    target = np.asarray(plan.target_m, float)
    normal = np.asarray(config.reference.plane_normal, float)
    normal /= np.linalg.norm(normal)
    incl = math.radians(plan.inclination_deg)
    poses = []
    for h in plan.heights_m:
        camera = look_at_pose(target, normal, h, incl, plan.tilt_axis)
        for az in plan.azimuths_deg:
            turn = Pose.from_xyz_rotvec(np.zeros(3), math.radians(az) * normal)
            about_target = Pose.from_rotation_matrix(turn.rotation_matrix, target - turn.apply_vector(target))
            poses.append(about_target @ camera @ mount_inv)
    return poses

"""``cellcal export --ros2 FILE [FILE ...]``: the cameras of results (or hand-eye files) as ROS 2 text.

Prints one ``static_transform_publisher`` launch file and a URDF joint per camera: ``T_flange_camera``
of a camera on the flange (a result.json or handeye.json), ``T_base_camera`` of a fixed camera
(``handeye-NAME.json``; ADR 0020, 0061). A result whose mount is the configured one (no
``[mount] from_handeye``) says so on stderr and in both texts. Exit status 2 for a file that is
not one of those, or two files for one camera frame.
"""

from __future__ import annotations

import argparse
import math
import re
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

from cellcal.core.cli.argtypes import path_arg
from cellcal.core.cli.exits import EXIT_OK
from cellcal.core.cli.options import check_input_file
from cellcal.core.console import say
from cellcal.devices.errors import ConfigError

if TYPE_CHECKING:
    from cellcal.devices.pose import Pose

#: Largest input read (a result.json with many poses stays far below), bytes.
MAX_INPUT_BYTES = 50 << 20
#: A ROS frame id / URDF link name this command writes into code and XML.
FRAME_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_/]{0,99}")


def _frame(text: str) -> str:
    if not FRAME_NAME.fullmatch(text):
        raise argparse.ArgumentTypeError(f"{text!r} is not a frame name (letters, digits, '_' and '/')")
    return text


def register(sub: Any) -> None:
    """Add the ``export`` subcommand."""
    p = sub.add_parser("export", help="print the cameras of results as ROS 2 launch and URDF text",
                       description="Read each camera's transform from 'cellcal calibrate' result.json or hand-eye "
                       "files (the mount, flange -> camera; a fixed camera's handeye-NAME.json: base -> camera) "
                       "and print one ROS 2 launch file with a static_transform_publisher per camera and a URDF "
                       "fixed joint for each. The camera frame is the optical frame (x right, y down, z forward).")
    p.add_argument("--ros2", metavar="FILE", required=True, nargs="+", type=path_arg,
                   help="result.json, handeye.json or handeye-NAME.json files, one per camera")
    p.add_argument("--parent", metavar="FRAME", default="flange", type=_frame,
                   help="parent frame / link of a camera on the flange (default: %(default)s)")
    p.add_argument("--base", metavar="FRAME", default="base_link", type=_frame,
                   help="parent frame / link of a fixed camera (default: %(default)s)")
    p.add_argument("--child", metavar="FRAME", default=None, type=_frame,
                   help="child frame / link of a single camera (default: its name in the file, else 'camera')")
    p.set_defaults(func=run)


#: Largest magnitude accepted per mount component: metres for a translation (a camera 10 m from its
#: flange is no mount), degrees for roll / pitch / yaw, 1 for a quaternion component.
MOUNT_BOUNDS = {"translation_m": 10.0, "rpy_deg": 360.0, "quaternion_xyzw": 1.0 + 1e-6}


def _vector(mount: Mapping[str, Any], key: str, size: int, source: str) -> list[float]:
    """``mount[key]`` as ``size`` finite numbers within :data:`MOUNT_BOUNDS` (ConfigError naming the key otherwise)."""
    import json  # here: an error message's, not at `cellcal --help`

    value = mount.get(key)
    items: list[Any] = value if isinstance(value, list) else []
    numbers = [v for v in items if isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)]
    if not isinstance(value, list) or len(value) != size or len(numbers) != size:
        raise ConfigError(f"must be a list of {size} finite numbers, got {json.dumps(value)[:80]}",
                          source=source, key=f"mount.{key}")
    bound = MOUNT_BOUNDS[key]
    if any(abs(v) > bound for v in numbers):
        if key == "quaternion_xyzw":  # a component beyond 1 is the first sign, not the whole story
            raise ConfigError(f"is not a unit quaternion (a component beyond +-1, got {json.dumps(value)[:80]})",
                              source=source, key=f"mount.{key}")
        raise ConfigError(f"has a component beyond +-{bound:g} (got {json.dumps(value)[:80]}): not a camera mount",
                          source=source, key=f"mount.{key}")
    return [float(v) for v in numbers]


def _printable(text: str, limit: int = 200) -> str:
    """``text`` as one printable line (control characters as ``?``), at most ``limit`` characters."""
    line = "".join(c if c.isprintable() else "?" for c in text)
    return line if len(line) <= limit else line[:limit - 3] + "..."


def configured_mount_note(document: Mapping[str, Any]) -> str | None:
    """Why the mount of a result document is not an estimate, or None when it is one (or cannot be told).

    A ``cellcal calibrate`` result carries its configuration: a ``[mount]`` with ``from_handeye``
    holds the hand-eye estimate, any other ``[mount]`` is the configured value, exported as it
    was typed. A ``cellcal handeye`` file is an estimate.
    """
    from cellcal.core.calibration.config import HANDEYE_SCHEMA_PREFIX
    from cellcal.core.calibration.report import RESULT_SCHEMA

    schema = str(document.get("schema", ""))
    if schema.startswith(HANDEYE_SCHEMA_PREFIX):
        return None
    config = document.get("config")
    if not schema.startswith(RESULT_SCHEMA.split("/")[0] + "/") and not isinstance(config, Mapping):
        return None  # a bare mount table: its origin is not recorded
    table = config.get("mount") if isinstance(config, Mapping) else None
    if isinstance(table, Mapping) and isinstance(table.get("from_handeye"), str):
        return None
    source = document.get("config_source")
    where = f" of {_printable(source)}" if isinstance(source, str) and source else ""
    return (f"this mount is the configured [mount]{where}, exported unchanged: nothing estimated it "
            "(estimate it with 'cellcal handeye', set [mount] from_handeye to its handeye.json, calibrate again)")


def read_document(path: str, need_mount: bool = True) -> dict[str, Any]:
    """The JSON object of ``path`` (with a ``mount`` object unless ``need_mount`` is False; ConfigError otherwise)."""
    from cellcal.devices import boundedjson  # here: json with it, not at `cellcal --help`

    check_input_file(path, MAX_INPUT_BYTES)
    try:
        with open(path, encoding="utf-8") as fh:
            document = boundedjson.loads(fh.read())
    except FileNotFoundError:
        raise ConfigError("file not found", source=path) from None
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise ConfigError(f"not a readable JSON file: {exc}", source=path) from None
    if not isinstance(document, dict):
        raise ConfigError("no 'mount' object (not a JSON object): expected a cellcal result.json or a hand-eye file",
                          source=path)
    if need_mount and not isinstance(document.get("mount"), dict):
        raise ConfigError("no 'mount' object: expected a cellcal result.json or a hand-eye file", source=path)
    return document


def read_mount(path: str) -> Pose:
    """``T_flange_camera`` from a result.json (``mount``: translation_m, quaternion_xyzw) or a
    hand-eye file (``mount``: translation_m, rpy_deg, as in a configuration's ``[mount]`` table).

    Raises:
        ConfigError: Naming the file and what is wrong with it.
    """
    return mount_pose(read_document(path), path)


def mount_pose(document: Mapping[str, Any], path: str) -> Pose:
    """``T_flange_camera`` of a document :func:`read_document` returned (``path`` for messages).

    Raises:
        ConfigError: Naming the file and what is wrong with its ``mount``.
    """
    import numpy as np
    from scipy.spatial.transform import Rotation

    from cellcal.devices.pose import Pose

    mount = document["mount"]
    translation = _vector(mount, "translation_m", 3, path)
    if "quaternion_xyzw" in mount:
        q = np.asarray(_vector(mount, "quaternion_xyzw", 4, path))
        # a stored unit quaternion (within 1e-6); anything else is not a rotation
        if abs(float(np.linalg.norm(q)) - 1.0) > 1e-6:
            raise ConfigError(f"is not a unit quaternion (norm {np.linalg.norm(q):.6g})", source=path,
                              key="mount.quaternion_xyzw")
        return Pose(Rotation.from_quat(q), np.asarray(translation))
    if "rpy_deg" in mount:
        return Pose.from_xyz_rpy(translation, np.radians(_vector(mount, "rpy_deg", 3, path)))
    raise ConfigError("needs 'quaternion_xyzw' (result.json) or 'rpy_deg' (hand-eye file)", source=path,
                      key="mount")


def _fixed_pose(document: Mapping[str, Any], path: str) -> Pose:
    """``T_base_camera`` of a fixed camera's result (``camera_base``), checked as a mount is."""
    table = document.get("camera_base")
    if not isinstance(table, Mapping):
        raise ConfigError("no 'camera_base' object: not a fixed camera's handeye-NAME.json", source=path)
    return mount_pose({"mount": {k: table.get(k) for k in ("translation_m", "quaternion_xyzw")}}, path)


def camera_transform(path: str, child: str | None, args: argparse.Namespace
                     ) -> tuple[Pose, str, str, str | None]:
    """``(pose, parent, child, note)`` of one file: a fixed camera under ``--base``, else the mount under ``--parent``.

    Raises:
        ConfigError: Naming the file and what is wrong with it.
    """
    from cellcal.core.handeye.fixed_run import FIXED_SCHEMA  # here: not at `cellcal --help`

    document = read_document(path, need_mount=False)
    name = document.get("camera")
    default = name if isinstance(name, str) and FRAME_NAME.fullmatch(name) else "camera"
    if str(document.get("schema", "")) == FIXED_SCHEMA:
        return _fixed_pose(document, path), args.base, child or default, None
    if not isinstance(document.get("mount"), dict):
        raise ConfigError("no 'mount' object: expected a cellcal result.json or a hand-eye file", source=path)
    return mount_pose(document, path), args.parent, child or default, configured_mount_note(document)


def run(args: argparse.Namespace) -> int:
    """Run ``cellcal export``; returns the exit status."""
    from cellcal.devices.recording.ros2.static import launch_file, urdf_joint

    paths = list(args.ros2)
    if args.child is not None and len(paths) > 1:
        raise ConfigError("--child names one camera's frame; with several files each takes its camera's name")
    transforms = [camera_transform(path, args.child, args) for path in paths]
    children = [t[2] for t in transforms]
    for k, child in enumerate(children):
        if children.index(child) != k:
            raise ConfigError(f"two files give camera frame {child!r} ({paths[children.index(child)]} and "
                              f"{paths[k]}): export each camera once")
    for _pose, _parent, _child, note in transforms:
        if note is not None:
            say(f"cellcal export: note: {note}")
    single = len(transforms) == 1
    print(launch_file([(pose, parent, child, "cellcal_mount" if single else f"cellcal_{child.replace('/', '_')}",
                        note) for pose, parent, child, note in transforms]))
    for k, (pose, parent, child, note) in enumerate(transforms):
        print(f"<!-- URDF fixed joint: {parent} -> {child} -->")
        print(urdf_joint(pose, parent, child, note=note), end="" if k == len(transforms) - 1 else "\n")
    return EXIT_OK

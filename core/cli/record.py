"""``cellcal record``: run the calibration plan and record the session to one MCAP file, or to a ROS 2 bag.

The library side is :mod:`cellcal.core.calibration.replay`; re-run a recording with
``cellcal calibrate --replay FILE.mcap``. An interrupted recording is finished with
what was recorded (ADR 0009). ``--format ros2`` writes a rosbag2 directory instead (ADR 0020).
"""

from __future__ import annotations

import argparse
import contextlib
import errno
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from cellcal.core.cli.argtypes import path_arg
from cellcal.core.cli.exits import EXIT_INTERRUPTED, EXIT_OK
from cellcal.core.cli.options import add_config_option, load_cell
from cellcal.core.cli.progress import progress_factory
from cellcal.core.console import say
from cellcal.devices.errors import CellcalError, ConfigError, OutputError

if TYPE_CHECKING:  # the calibration and the recorder are imported by run(), not by `cellcal --help`
    from cellcal.core.calibration.calibrator import PoseObserver
    from cellcal.core.calibration.config import CellConfig
    from cellcal.devices.camera import Camera3D
    from cellcal.devices.recording import SessionRecorder
    from cellcal.devices.recording.ros2 import Ros2BagWriter
    from cellcal.devices.recording.scene import Scene
    from cellcal.devices.safety import SafeArm


def register(sub: Any) -> None:
    """Add the ``record`` subcommand."""
    p = sub.add_parser("record", help="run the calibration plan and record the session to an MCAP file "
                       "or a ROS 2 bag",
                       description="Run the calibration plan like 'cellcal calibrate' and record the session "
                       "(configuration, frames, arm calls, result, and the 3D scene: point cloud, fitted plane, "
                       "frames) to one MCAP file, readable in Foxglove. Re-run it anywhere with: cellcal calibrate "
                       "--replay FILE.mcap. With --format ros2, write a ROS 2 bag directory (tf, camera info, "
                       "depth image, point cloud, plane) instead. An interrupted run (Ctrl-C) keeps the "
                       "recording of what happened until then.")
    add_config_option(p)
    p.add_argument("--out", metavar="FILE.mcap|DIR", required=True, type=path_arg,
                   help="recording to write: an MCAP file, or with --format ros2 a new bag directory")
    p.add_argument("--format", choices=("mcap", "ros2"), default="mcap",
                   help="mcap: cellcal's replayable recording (default); ros2: a rosbag2 directory for "
                   "'ros2 bag play' (not replayable by cellcal)")
    p.add_argument("--result", metavar="DIR", type=path_arg, help="also write DIR/result.json")
    p.add_argument("--keep-failed", action="store_true",
                   help="keep the recording of a run that fails with a device or calibration error "
                   "(default: discard it)")
    p.add_argument("--quiet", action="store_true", help="no progress bar or summary; only the paths written")
    p.set_defaults(func=run)


def _config_text(path: str | None) -> str | None:
    """The TOML text of the configuration, stored in the recording for humans."""
    from cellcal.core.calibration.config import read_config_text

    try:
        return read_config_text(path)[0]
    except ConfigError:  # already read once by load_config; not worth failing over
        return None


def _interrupted(recorder: SessionRecorder) -> str:
    """The line saying what became of the recording of an interrupted run."""
    from cellcal.devices.recording.schema import TOPIC_ARM_CALL, TOPIC_CAPTURE

    if recorder.finished:
        counts = recorder.message_counts
        return (f"cellcal: interrupted; the recording of the run so far ({counts[TOPIC_CAPTURE]} captures, "
                f"{counts[TOPIC_ARM_CALL]} arm calls, no result) is in {recorder.path}")
    return f"cellcal: interrupted; the recording could not be finished: {recorder.finish_error}"


def scene_observer(config: CellConfig, sink: Callable[[Scene], None]) -> PoseObserver:
    """A calibrator observer handing the scene of every frame of every measured pose to ``sink``."""
    from cellcal.core.liveview.scenes import calibration_scenes

    mount = config.mount.pose()

    def observer(record: Any, frames: Any, result: Any) -> None:
        for scene in calibration_scenes(record, frames, result, mount):
            sink(scene)

    return observer


def _bag_interrupted(bag: Ros2BagWriter) -> str:
    """The line saying what became of the ROS 2 bag of an interrupted run."""
    what = f"the bag of the run so far is in {bag.path}" if bag.finished else "no bag was written"
    return f"cellcal: interrupted; {what}"


def _record(args: argparse.Namespace, out: Path, open_sink: Callable[[], Any], run_into: Callable[[Any], Any],
            interrupted: Callable[[Any], str]) -> tuple[Any, int]:
    """Lock the outputs, run the plan into a writer (its ``with`` block), write ``--result``.

    Args:
        args: The command line.
        out: The recording (file or bag directory).
        open_sink: Creates the writer (a :class:`SessionRecorder` or a :class:`Ros2BagWriter`).
        run_into: Runs the plan into the writer; returns the result document.
        interrupted: The line to print when Ctrl-C ends the run.

    Returns:
        The (closed) writer and the exit status (0, or 130 after Ctrl-C).
    """
    from cellcal.core.calibration.outlock import OutputLock
    from cellcal.core.calibration.report import RESULT_FILENAME, write_json_atomic

    with contextlib.ExitStack() as locks:
        locks.enter_context(OutputLock.for_file(out))
        if args.result:
            locks.enter_context(OutputLock.for_directory(args.result))
        sink = open_sink()
        try:
            with sink:
                document = run_into(sink)
        except KeyboardInterrupt:
            say(interrupted(sink))
            return sink, EXIT_INTERRUPTED
        except CellcalError:
            if sink.finished:
                say(f"recording of the failed run written to {out}")
            raise
        if args.result:
            print(f"result written to {write_json_atomic(Path(args.result) / RESULT_FILENAME, document)}")
    return sink, EXIT_OK


def _run_ros2(args: argparse.Namespace, config: CellConfig, camera: Camera3D, safe_arm: SafeArm) -> int:
    """``--format ros2``: run the plan and write the scenes to a new rosbag2 directory ``--out``."""
    from cellcal.core.calibration.calibrator import Calibrator
    from cellcal.devices.recording.ros2 import Ros2BagWriter

    out = Path(args.out)
    bag, status = _record(args, out, lambda: Ros2BagWriter(out, keep_on_error=args.keep_failed),
                          lambda bag: Calibrator(config, camera, safe_arm,
                                                 progress=progress_factory("poses", "pose", args.quiet),
                                                 observer=scene_observer(config, bag.write_scene)).run(),
                          _bag_interrupted)
    if status != EXIT_OK:
        return status
    if not args.quiet:
        size = sum(f.stat().st_size for f in out.iterdir())
        print(f"{sum(bag.message_counts.values())} messages, {size / 1e6:.2f} MB; play with: ros2 bag play {out}")
    print(f"ROS 2 bag written to {out}")
    return EXIT_OK


def run(args: argparse.Namespace) -> int:
    """Run ``cellcal record``; returns the exit status."""
    from cellcal.core.calibration.calibrator import build_devices
    from cellcal.core.calibration.replay import run_recorded
    from cellcal.devices.recording import SessionRecorder

    config = load_cell(args)
    camera, safe_arm = build_devices(config)
    if getattr(args, "format", "mcap") == "ros2":
        return _run_ros2(args, config, camera, safe_arm)
    out = Path(args.out)
    if out.is_dir():
        raise OutputError(f"{out} is a directory; --out takes the recording's file name, e.g. session.mcap",
                          errno=errno.EISDIR)
    recorder, status = _record(
        args, out, lambda: SessionRecorder(out, config_document=config.document, config_source=config.source,
                                           config_text=_config_text(args.config), keep_on_error=args.keep_failed),
        lambda rec: run_recorded(config, rec, camera, safe_arm, progress=progress_factory("poses", "pose", args.quiet),
                                 observer=scene_observer(config, rec.log_scene)),
        _interrupted)
    if status != EXIT_OK:
        return status
    if not args.quiet:
        size = out.stat().st_size
        print(f"{sum(recorder.message_counts.values())} messages, {size / 1e6:.2f} MB; "
              f"re-run with: cellcal calibrate --replay {out}")
    print(f"recording written to {out}")
    return EXIT_OK


def open_recorder(stack: contextlib.ExitStack, path: str, config: CellConfig, config_path: str | None
                  ) -> SessionRecorder:
    """A session recorder writing ``path`` (``--record`` of calibrate's siblings), entered on ``stack``.

    The file is locked for the run; the configuration's text is recorded as it was read.
    """
    from cellcal.core.calibration.config import read_config_text
    from cellcal.core.calibration.outlock import OutputLock
    from cellcal.devices.recording import SessionRecorder

    stack.enter_context(OutputLock.for_file(path))
    return stack.enter_context(SessionRecorder(path, config_document=config.document, config_source=config.source,
                                               config_text=read_config_text(config_path)[0]))

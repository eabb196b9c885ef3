"""The session recorder: one MCAP file, written atomically, that its device wrappers log into."""

from __future__ import annotations

import contextlib
import json
import os
import tempfile
import threading
import time
from collections.abc import Mapping
from pathlib import Path
from types import TracebackType
from typing import Any, Self

from cellcal.devices.arm import RobotArm
from cellcal.devices.camera import Camera3D
from cellcal.devices.errors import CellcalError, RecordingError, RecordingWriteError
from cellcal.devices.interrupts import interrupts_held
from cellcal.devices.version import cellcal_version

from .codec import dumps, encode_error, seconds_to_ns
from .foxglove import scene_messages
from .scene import Scene
from .schema import (
    CHANNELS,
    MCAP_PROFILE,
    RECORDING_FORMAT,
    SCENE_CHANNELS,
    SCENE_SCHEMAS,
    SCHEMAS,
    TOPIC_POINTS,
    TOPIC_RESULT,
    TOPIC_SESSION,
    import_mcap,
)
from .wrappers import RecordingArm, RecordingCamera


class SessionRecorder:
    """Writes one session to an MCAP file; wrap the devices with :meth:`camera` and :meth:`arm`.

    The file is written under a temporary name in the destination directory and
    renamed to ``path`` by :meth:`close`; :meth:`abort` (and leaving the ``with``
    block on an exception) deletes it, so ``path`` never holds a torn recording.
    An interrupted session (KeyboardInterrupt) is the exception: the file is finished
    with what was recorded and an ``ok = false`` result naming the interruption, and
    :attr:`finished` says whether that worked (ADR 0009). Ctrl-C is held back while a
    message or the file's end is being written, so it never tears a record.

    Args:
        path: Destination ``.mcap`` file.
        config_document: The cell configuration document (stored as JSON).
        config_source: Where the configuration came from (for humans).
        config_text: The configuration's TOML text, if available (for humans).
        keep_on_error: When leaving the ``with`` block on a :class:`CellcalError` that
            is not a :class:`RecordingError` (e.g. a device fault during the run), finish
            the file (with the error logged) instead of discarding it.
        compression: ``"zstd"`` (default), ``"lz4"`` or ``"none"`` for the MCAP chunks.

    Raises:
        MissingDependencyError: If ``mcap`` (extra ``record``) is not installed.
        RecordingWriteError: If the file cannot be created.
    """

    def __init__(self, path: str | Path, *, config_document: Mapping[str, Any] | None = None,
                 config_source: str | None = None, config_text: str | None = None,
                 keep_on_error: bool = False, compression: str = "zstd") -> None:
        writer_mod, _ = import_mcap()
        kinds = {"zstd": writer_mod.CompressionType.ZSTD, "lz4": writer_mod.CompressionType.LZ4,
                 "none": writer_mod.CompressionType.NONE}
        if compression not in kinds:
            raise RecordingError(f"compression must be one of {', '.join(kinds)}, got {compression!r}")
        self.path = Path(path)
        self.keep_on_error = keep_on_error
        self._lock = threading.RLock()
        self._event = 0
        self._result_logged = False
        #: Whether the file was finished and moved to :attr:`path`.
        self.finished = False
        #: Why finishing an interrupted session's file failed, if it did.
        self.finish_error: BaseException | None = None
        self.message_counts: dict[str, int] = dict.fromkeys(CHANNELS, 0)
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            fd, tmp = tempfile.mkstemp(prefix=f".{self.path.name}.", suffix=".tmp", dir=self.path.parent)
        except OSError as exc:
            raise RecordingWriteError(f"cannot write {self.path}: {exc.strerror or exc}", errno=exc.errno) from None
        self._tmp: Path | None = Path(tmp)
        self._fh = os.fdopen(fd, "wb")
        try:
            self._writer = writer_mod.Writer(self._fh, compression=kinds[compression])
            self._start(config_document, config_source, config_text)
        except BaseException:
            self.abort()
            raise

    def _start(self, config_document: Mapping[str, Any] | None, config_source: str | None,
               config_text: str | None) -> None:
        """Write the MCAP header, every schema and channel, the metadata and the ``/cellcal/session`` message."""
        version = cellcal_version()
        self._writer.start(profile=MCAP_PROFILE, library=f"cellcal {version}")
        schema_ids = {name: self._writer.register_schema(name=name, encoding="jsonschema",
                                                         data=json.dumps(schema).encode("utf-8"))
                      for name, schema in SCHEMAS.items()}
        self._channels = {topic: self._writer.register_channel(topic=topic, message_encoding="json",
                                                               schema_id=schema_ids[schema])
                          for topic, schema in CHANNELS.items()}
        self._writer.add_metadata("cellcal", {"format": RECORDING_FORMAT, "cellcal_version": version})
        self.log(TOPIC_SESSION, {
            "format": RECORDING_FORMAT, "cellcal_version": version,
            "created_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
            "config_source": config_source,
            "config": None if config_document is None else dict(config_document),
            "config_toml": config_text,
        })

    # ------------------------------------------------------------ wrapping
    def camera(self, camera: Camera3D) -> RecordingCamera:
        """``camera`` behind a recording wrapper (drive its life cycle through the wrapper)."""
        return RecordingCamera(camera, self)

    def arm(self, arm: RobotArm) -> RecordingArm:
        """``arm`` behind a recording wrapper; put any :class:`SafeArm` *around* it."""
        return RecordingArm(arm, self)

    # ------------------------------------------------------------ logging
    @property
    def closed(self) -> bool:
        """Whether the file has been finished or discarded."""
        return self._tmp is None

    def next_event(self) -> int:
        """Reserve the next session-wide event number (the replay order)."""
        with self._lock:
            self._event += 1
            return self._event

    def log(self, topic: str, payload: Mapping[str, Any], *, event: int | None = None,
            publish_time_s: float | None = None) -> None:
        """Write one JSON message on ``topic`` (log time: now).

        Raises:
            RecordingError: If the recorder is closed.
            RecordingWriteError: If the write fails (disk full ...).
        """
        now = time.time_ns()
        publish = seconds_to_ns(publish_time_s) or now
        with self._lock:
            if self._tmp is None:
                raise RecordingError(f"recorder for {self.path} is closed; nothing more can be logged")
            seq = self.next_event() if event is None else event
            numbered = "event" in SCHEMAS.get(CHANNELS.get(topic, ""), {}).get("properties", {})
            data = dumps({**payload, "event": seq} if numbered else payload)
            try:
                with interrupts_held():
                    self._writer.add_message(channel_id=self._channels[topic], log_time=now, data=data,
                                             publish_time=publish, sequence=seq)
                    self.message_counts[topic] = self.message_counts.get(topic, 0) + 1
            except OSError as exc:
                raise RecordingWriteError(f"cannot write {self.path}: {exc.strerror or exc}", errno=exc.errno) from None

    def log_scene(self, scene: Scene) -> None:
        """Write the scene of one frame: point cloud, fitted plane and frames (ADR 0020).

        The scene channels are added to the file with the first scene, so a session
        recorded without scenes has exactly the channels of ADR 0009.

        Raises:
            RecordingError: If the recorder is closed.
            RecordingWriteError: If the write fails (disk full ...).
        """
        with self._lock:
            if self._tmp is not None and TOPIC_POINTS not in self._channels:
                with interrupts_held():
                    for topic, name in SCENE_CHANNELS.items():
                        schema_id = self._writer.register_schema(
                            name=name, encoding="jsonschema", data=json.dumps(SCENE_SCHEMAS[name]).encode("utf-8"))
                        self._channels[topic] = self._writer.register_channel(
                            topic=topic, message_encoding="json", schema_id=schema_id)
        for topic, payload in scene_messages(scene).items():
            if topic in SCENE_CHANNELS:  # a monitor's drift values are for the live view
                self.log(topic, payload, publish_time_s=scene.timestamp)

    def log_result(self, document: Mapping[str, Any] | None, error: CellcalError | None = None) -> None:
        """Store the run's outcome: the calibration result document, or the error it ended with."""
        self.log(TOPIC_RESULT, {"ok": error is None, "result": None if document is None else dict(document),
                                "error": None if error is None else encode_error(error)})
        self._result_logged = True

    def log_interrupted(self) -> None:
        """Store that the run was interrupted (Ctrl-C) before it had a result."""
        self.log(TOPIC_RESULT, {"ok": False, "result": None, "error": encode_error(KeyboardInterrupt())})
        self._result_logged = True

    # ------------------------------------------------------------ finishing
    def close(self) -> Path:
        """Finish the file and move it to :attr:`path`; returns the path. Idempotent.

        Raises:
            RecordingWriteError: If finishing or renaming fails (the temporary file is removed).
        """
        with self._lock:
            if self._tmp is None:
                return self.path
            try:
                with interrupts_held():
                    self._writer.finish()
                    self._fh.flush()
                    os.fsync(self._fh.fileno())
                    self._fh.close()
                    umask = os.umask(0)
                    os.umask(umask)
                    os.chmod(self._tmp, 0o666 & ~umask)  # mkstemp made it private; give it normal permissions
                    os.replace(self._tmp, self.path)
                    self._tmp = None
                    self.finished = True
            except BaseException as exc:
                self.abort()
                if isinstance(exc, OSError):
                    raise RecordingWriteError(f"cannot write {self.path}: {exc.strerror or exc}",
                                              errno=exc.errno) from None
                raise
        return self.path

    def abort(self) -> None:
        """Discard the recording: close and delete the temporary file. Idempotent."""
        with self._lock:
            tmp, self._tmp = self._tmp, None
            if tmp is None:
                return
            with contextlib.suppress(OSError):
                self._fh.close()
            tmp.unlink(missing_ok=True)

    def __enter__(self) -> Self:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        if exc is None:
            self.close()
        elif isinstance(exc, KeyboardInterrupt):
            self._finish_interrupted()
        elif self.keep_on_error and isinstance(exc, CellcalError) and not isinstance(exc, RecordingError):
            try:
                if not self._result_logged:
                    self.log_result(None, exc)
                self.close()
            except BaseException:
                self.abort()
                raise
        else:
            self.abort()

    def _finish_interrupted(self) -> None:
        """Finish the file of an interrupted session; a failure is kept in :attr:`finish_error`, not raised.

        The interruption goes on propagating either way (the caller reports both).
        """
        try:
            if not self._result_logged:
                self.log_interrupted()
            self.close()
        except Exception as exc:  # reported through finish_error: the Ctrl-C goes on regardless
            self.finish_error = exc
            self.abort()

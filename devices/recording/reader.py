"""Reading a recording back: :func:`read_recording` checks an MCAP file and parses it into a :class:`Recording`."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, BinaryIO

from cellcal.devices.errors import RecordingFileError

from .schema import (
    MCAP_MAGIC,
    READABLE_FORMATS,
    TOPIC_ARM_CALL,
    TOPIC_ARM_INFO,
    TOPIC_CAMERA_INFO,
    TOPIC_CAPTURE,
    TOPIC_RESULT,
    TOPIC_SESSION,
    import_mcap,
)

#: Messages of one topic: (event number, payload).
_Messages = list[tuple[int, dict[str, Any]]]


@dataclass
class Recording:
    """A parsed recording, in event order.

    Attributes:
        path: The file it was read from.
        session: The ``/cellcal/session`` payload (format, versions, config document).
        camera_infos: ``/camera/info`` payloads, one per connect.
        arm_infos: ``/arm/info`` payloads, one per connect.
        captures: ``/camera/capture`` payloads (``frame`` still encoded; see :func:`decode_frame`).
        arm_calls: ``/arm/call`` payloads.
        result: The last ``/cellcal/result`` payload, or None.
        message_counts: Messages per topic, as stored.
    """

    path: Path
    session: dict[str, Any]
    camera_infos: list[dict[str, Any]] = field(default_factory=list)
    arm_infos: list[dict[str, Any]] = field(default_factory=list)
    captures: list[dict[str, Any]] = field(default_factory=list)
    arm_calls: list[dict[str, Any]] = field(default_factory=list)
    result: dict[str, Any] | None = None
    message_counts: dict[str, int] = field(default_factory=dict)

    @property
    def format(self) -> str:
        """The recording's format tag (one of :data:`~cellcal.devices.recording.schema.READABLE_FORMATS`)."""
        return str(self.session.get("format"))

    @property
    def config_document(self) -> dict[str, Any] | None:
        """The recorded configuration document, or None when none was recorded."""
        doc = self.session.get("config")
        return doc if isinstance(doc, dict) else None

    @property
    def config_source(self) -> str | None:
        """Where the recorded configuration came from."""
        src = self.session.get("config_source")
        return src if isinstance(src, str) else None


_TOPIC_LISTS = {TOPIC_CAMERA_INFO: "camera_infos", TOPIC_ARM_INFO: "arm_infos", TOPIC_CAPTURE: "captures",
                TOPIC_ARM_CALL: "arm_calls"}


def read_recording(path: str | Path) -> Recording:
    """Read and check a recording written by :class:`SessionRecorder`.

    Raises:
        MissingDependencyError: If ``mcap`` (extra ``record``) is not installed.
        RecordingFileError: If the file is missing, unreadable, not MCAP, truncated,
            corrupt (CRC), or not a cellcal recording of a supported format — one line
            naming the file.
    """
    _, reader_mod = import_mcap()
    p = Path(path)
    source = str(p)
    if not p.is_file():
        raise RecordingFileError("recording not found" if not p.exists() else "not a file", source=source)
    try:
        fh = p.open("rb")
    except OSError as exc:
        raise RecordingFileError(f"cannot read: {exc.strerror or exc}", source=source) from None
    with fh:
        by_topic = _messages_by_topic(fh, reader_mod, source)
    session = _session(by_topic, source)
    rec = Recording(path=p, session=session,
                    message_counts={topic: len(msgs) for topic, msgs in by_topic.items()})
    for topic, attr in _TOPIC_LISTS.items():
        setattr(rec, attr, [payload for _, payload in sorted(by_topic.get(topic, []), key=lambda m: m[0])])
    results = sorted(by_topic.get(TOPIC_RESULT, []), key=lambda m: m[0])
    rec.result = results[-1][1] if results else None
    return rec


def _messages_by_topic(fh: BinaryIO, reader_mod: Any, source: str) -> dict[str, _Messages]:
    """Every message of the open file ``fh``, by topic, as (MCAP sequence, JSON payload), CRCs checked.

    Raises:
        RecordingFileError: If the file is not MCAP, is truncated or corrupt, or holds a non-object message.
    """
    by_topic: dict[str, _Messages] = {}
    try:
        if fh.read(len(MCAP_MAGIC)) != MCAP_MAGIC:
            raise RecordingFileError("not an MCAP file (it does not start with the MCAP magic bytes)",
                                     source=source)
        fh.seek(0)
        reader = reader_mod.make_reader(fh, validate_crcs=True)
        for _schema, channel, message in reader.iter_messages(log_time_order=False):
            payload = json.loads(message.data)
            if not isinstance(payload, dict):
                raise ValueError(f"message on {channel.topic} is not a JSON object")
            by_topic.setdefault(channel.topic, []).append((int(message.sequence), payload))
    except RecordingFileError:
        raise
    except Exception as exc:  # mcap, zstd, json, struct, seek past the start ... all mean one thing here
        detail = str(exc).splitlines()[0][:200] if str(exc) else ""
        raise RecordingFileError(f"not a readable MCAP recording (truncated or corrupt?): "
                                 f"{type(exc).__name__}{': ' + detail if detail else ''}", source=source) from None
    return by_topic


def _session(by_topic: dict[str, _Messages], source: str) -> dict[str, Any]:
    """The first ``/cellcal/session`` payload, checked to be of a format this cellcal reads.

    Raises:
        RecordingFileError: If there is none, or its format is another one.
    """
    sessions = by_topic.get(TOPIC_SESSION, [])
    if not sessions:
        raise RecordingFileError(f"MCAP file has no {TOPIC_SESSION} message: not a cellcal recording", source=source)
    session = sessions[0][1]
    if session.get("format") not in READABLE_FORMATS:
        raise RecordingFileError(f"recording format {session.get('format')!r} is not supported "
                                 f"(this cellcal reads {', '.join(repr(f) for f in READABLE_FORMATS)})",
                                 source=source)
    return session

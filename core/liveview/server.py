"""The live view: a Foxglove WebSocket server (foxglove-sdk) streaming the scene of every frame (ADR 0020)."""

from __future__ import annotations

import json
import socket
import threading
import time
from collections.abc import Sequence
from types import TracebackType
from typing import TYPE_CHECKING, Any, Self

from cellcal.core.console import say
from cellcal.core.liveview.sdklog import flush_sdk_log, route_sdk_logging
from cellcal.core.liveview.subprotocol import SubprotocolRelay
from cellcal.devices.errors import ConfigError
from cellcal.devices.pose import Pose
from cellcal.devices.recording.codec import dumps, seconds_to_ns
from cellcal.devices.recording.foxglove import pose_json, scene_messages, stamp
from cellcal.devices.recording.scene import BASE_FRAME_ID, CAMERA_FRAME_ID, Scene
from cellcal.devices.recording.schema import (
    DRIFT_CHANNELS,
    SCENE_CHANNELS,
    SCENE_SCHEMAS,
    TOPIC_PLANE,
    TOPIC_POINTS,
    TOPIC_TF,
    TRACK_CHANNELS,
)

if TYPE_CHECKING:
    from cellcal.core.calibration.calibrator import PoseRecord
    from cellcal.core.methods.fullframe import FullFrameResult
    from cellcal.devices.types import Frame

__all__ = ["HOST", "LiveView", "camera_frame_id", "camera_topics", "import_foxglove", "open_live_view"]

#: The live view listens on the loopback interface only.
HOST = "127.0.0.1"
#: Name the server gives itself in Foxglove's connection list.
SERVER_NAME = "cellcal"
#: Longest wait in :meth:`LiveView.close` for the SDK to release the port, s.
RELEASE_TIMEOUT_S = 2.0
#: Most viewers connected at once; more are closed as they connect (ADR 0039).
MAX_CLIENTS = 8
#: Messages the SDK queues per client before it drops the oldest data message (ADR 0039).
MESSAGE_BACKLOG = 16


def camera_frame_id(name: str) -> str:
    """The frame id of camera ``name`` of a cell with several cameras (``camera_NAME``; one camera: ``camera``)."""
    return f"{CAMERA_FRAME_ID}_{name}"


def camera_topics(name: str) -> dict[str, str]:
    """Camera ``name``'s own topics for its cloud and plane, by the one-camera topic they replace.

    A viewer keeps the last message of a topic: each camera of several has its own, so that every
    camera's cloud and plane are drawn at once (ADR 0061).
    """
    return {TOPIC_POINTS: f"/cameras/{name}/points", TOPIC_PLANE: f"/cameras/{name}/plane"}


def import_foxglove() -> Any:
    """The ``foxglove`` SDK module.

    Raises:
        ConfigError: If foxglove-sdk (extra ``viz``) is not installed (``--viz-port`` is then bad input).
    """
    try:
        import foxglove
    except ImportError:
        raise ConfigError("--viz-port needs foxglove-sdk, which is not installed: "
                          "pip install 'cellcal[viz]'") from None
    return foxglove


class _Subscriptions:
    """The SDK's server listener: counts the subscriptions clients have made (called from the SDK's thread)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.count = 0

    def on_subscribe(self, client: Any, channel: Any) -> None:
        """A client subscribed (the SDK has registered it: the channel has a sink)."""
        with self._lock:
            self.count += 1

    def on_unsubscribe(self, client: Any, channel: Any) -> None:
        """A client unsubscribed or left (the SDK calls this too; nothing to do)."""


class LiveView:
    """Serves the Foxglove WebSocket protocol on ``127.0.0.1:port`` and publishes scenes.

    Channels (JSON, schemas by Foxglove's names): ``/camera/points`` (``foxglove.PointCloud``,
    inliers green, outliers red), ``/cellcal/plane`` (``foxglove.SceneUpdate``: the fitted
    plane and its normal), ``/tf`` (``foxglove.FrameTransforms``: base, flange, camera) and,
    with ``drift=True``, ``/cellcal/drift`` (``cellcal.Drift``), with ``track=True`` ``/cellcal/track``
    (``cellcal.Track``). With ``cameras`` (a cell's several cameras) each camera has its own cloud and
    plane topics (:func:`camera_topics`) and frame id (:func:`camera_frame_id`); ``/tf`` holds each
    camera's frame: under the flange with its mount, or under the base (:meth:`place_camera`) for a fixed
    one. A message reaches the clients
    subscribed at the time it is published; the last scene of each camera is kept, so
    :meth:`republish` can show it to a client that subscribes later (ADR 0035).

    The SDK listens on an ephemeral loopback port; the user's port is a
    :class:`~cellcal.core.liveview.subprotocol.SubprotocolRelay` in front of it, which admits
    clients offering either name of the protocol and at most :data:`MAX_CLIENTS` at once. Each
    client's queue holds :data:`MESSAGE_BACKLOG` messages (the oldest is dropped), so a viewer
    that does not read costs bounded memory and never holds the run up (ADR 0039).

    Args:
        port: TCP port (0: any free port; see :attr:`port`).
        drift: Also advertise the drift channel (the monitor).
        track: Also advertise the track channel (``cellcal track``).
        cameras: The names of a cell's several cameras (their own topics); empty: one camera.

    Raises:
        ConfigError: If foxglove-sdk is not installed or the port cannot be listened on.
    """

    def __init__(self, port: int, *, drift: bool = False, track: bool = False, cameras: Sequence[str] = ()
                 ) -> None:
        foxglove = import_foxglove()
        route_sdk_logging()
        self._context = foxglove.Context()
        topics = {**SCENE_CHANNELS, **(DRIFT_CHANNELS if drift else {}), **(TRACK_CHANNELS if track else {})}
        #: Each camera's topics by its frame id (a cell's several cameras), and the fixed ones' T_base_camera.
        self._routes = {camera_frame_id(name): camera_topics(name) for name in cameras}
        self._fixed: dict[str, Pose] = {}
        for route in self._routes.values():  # each camera's cloud and plane instead of the shared ones
            topics.update({own: SCENE_CHANNELS[shared] for shared, own in route.items()})
        if self._routes:
            topics = {t: name for t, name in topics.items() if t not in (TOPIC_POINTS, TOPIC_PLANE)}
        self._subscriptions = _Subscriptions()
        self._last: dict[str, Scene] = {}
        self._channels = {topic: foxglove.Channel(topic, schema=foxglove.Schema(
            name=name, encoding="jsonschema", data=json.dumps(SCENE_SCHEMAS[name]).encode("utf-8")),
            message_encoding="json", context=self._context) for topic, name in topics.items()}
        try:  # the SDK on a port of its own; the user's port is the relay's
            self._server = foxglove.start_server(name=SERVER_NAME, host=HOST, port=0, context=self._context,
                                                 server_listener=self._subscriptions,
                                                 message_backlog_size=MESSAGE_BACKLOG)
        except Exception as exc:  # the SDK raises its own error type when it cannot listen
            self._close_channels()
            raise ConfigError(f"--viz-port {port}: the live view's server cannot start: {exc}") from None
        #: The SDK server's own (ephemeral, loopback) port, behind the relay.
        self.upstream_port = int(self._server.port)
        try:
            self._relay: SubprotocolRelay | None = SubprotocolRelay(HOST, port, self.upstream_port,
                                                                    max_clients=MAX_CLIENTS)
        except (OSError, OverflowError) as exc:  # in use, not allowed, or out of range
            self._server.stop()
            self._close_channels()
            reason = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
            raise ConfigError(f"--viz-port {port}: cannot listen on {HOST}:{port}: {reason}") from None
        #: The port viewers connect to (the relay's).
        self.port = self._relay.port
        #: Messages published per topic (to at least one subscribed client).
        self.message_counts: dict[str, int] = dict.fromkeys(topics, 0)

    @property
    def url(self) -> str:
        """The WebSocket URL to open in Foxglove."""
        return f"ws://{HOST}:{self.port}"

    @property
    def subscriptions(self) -> int:
        """How many subscriptions clients have made so far (a count that only grows)."""
        return self._subscriptions.count

    def has_subscribers(self) -> bool:
        """Whether a client is subscribed to any channel now."""
        return any(channel.has_sinks() for channel in self._channels.values())

    def all_subscribed(self) -> bool:
        """Whether every channel has a subscribed client now."""
        return all(channel.has_sinks() for channel in self._channels.values())

    def republish(self) -> None:
        """Publish again the last scene of each camera (for clients that subscribed after it was published)."""
        for scene in list(self._last.values()):
            self._send(scene)

    def publish(self, scene: Scene) -> None:
        """Publish one scene on every channel it has data for (log time: the frame's time), and keep it
        as its camera's last scene.

        Nothing is encoded while no client subscribes to any channel.
        """
        self._last[scene.camera_frame_id] = scene
        self._send(scene)

    def place_camera(self, frame_id: str, base_camera: Pose) -> None:
        """Say that the camera of ``frame_id`` is fixed at ``T_base_camera``: its scenes add it to ``/tf``."""
        self._fixed[frame_id] = base_camera

    def _messages(self, scene: Scene) -> dict[str, dict[str, Any]]:
        """The scene's messages by topic: on its camera's own topics, with a fixed camera's transform in ``/tf``."""
        messages = scene_messages(scene)
        fixed = self._fixed.get(scene.camera_frame_id)
        if fixed is not None:
            p = pose_json(fixed)
            tf = messages.setdefault(TOPIC_TF, {"transforms": []})
            tf["transforms"].append({"timestamp": stamp(scene.timestamp), "parent_frame_id": BASE_FRAME_ID,
                                     "child_frame_id": scene.camera_frame_id, "translation": p["position"],
                                     "rotation": p["orientation"]})
        route = self._routes.get(scene.camera_frame_id, {})
        return {route.get(topic, topic): payload for topic, payload in messages.items()}

    def _send(self, scene: Scene) -> None:
        if not any(channel.has_sinks() for channel in self._channels.values()):
            return
        log_time = seconds_to_ns(scene.timestamp) or None
        for topic, payload in self._messages(scene).items():
            channel = self._channels.get(topic)
            if channel is not None and channel.has_sinks():
                channel.log(dumps(payload), log_time=log_time)
                self.message_counts[topic] += 1

    def observe_pose(self, mount: Pose | None, camera: str | None = None) -> Any:
        """A :data:`~cellcal.core.calibration.calibrator.PoseObserver` publishing each pose's scenes.

        Args:
            mount: ``T_flange_camera``; None: a fixed camera, already placed (:meth:`place_camera`).
            camera: A cell's camera name (its frame ``camera_NAME`` and its own topics); None: the one camera.
        """
        from cellcal.core.liveview.scenes import calibration_scenes

        frame_id = CAMERA_FRAME_ID if camera is None else camera_frame_id(camera)

        def observer(record: PoseRecord, frames: Sequence[Frame], result: FullFrameResult | None) -> None:
            for scene in calibration_scenes(record, frames, result, mount, camera_frame_id=frame_id):
                self.publish(scene)

        return observer

    def close(self) -> None:
        """Stop the server, close the channels, and wait (at most :data:`RELEASE_TIMEOUT_S`) for the
        port to be released, so a next run can listen on it at once. Idempotent."""
        relay, self._relay = self._relay, None
        if relay is not None:
            relay.close(RELEASE_TIMEOUT_S)  # closes the user's port and every viewer's connection
        server, self._server = self._server, None
        if server is not None:
            server.stop()  # asynchronous: the SDK's runtime drops its listener a moment later
        self._close_channels()
        if relay is not None:
            _wait_until_released(self.port, time.monotonic() + RELEASE_TIMEOUT_S)
        flush_sdk_log()  # say how many of the SDK's records were held back, if any

    def _close_channels(self) -> None:
        for channel in self._channels.values():
            channel.close()
        self._channels = {}

    def __enter__(self) -> Self:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()


def _wait_until_released(port: int, deadline: float) -> None:
    """Return once nothing listens on ``HOST:port`` (a test bind succeeds) or ``deadline`` passes."""
    while True:
        with socket.socket() as probe:
            probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # TIME_WAIT connections do not count
            try:
                probe.bind((HOST, port))
                return
            except OSError:
                if time.monotonic() >= deadline:
                    return
        time.sleep(0.002)


def open_live_view(port: int | None, *, drift: bool = False, track: bool = False, cameras: Sequence[str] = ()
                   ) -> LiveView | None:
    """Start the live view of ``--viz-port`` (None: no live view) and say on stderr where to connect.

    Raises:
        ConfigError: If foxglove-sdk is not installed or the port cannot be listened on.
    """
    if port is None:
        return None
    view = LiveView(port, drift=drift, track=track, cameras=cameras)
    say(f"live view: {view.url} (in Foxglove: Open connection, Foxglove WebSocket, this URL)")
    return view

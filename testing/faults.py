"""Fault injection on a simulated cell: timeouts, disconnects, stalls, bad frames, arm errors (:class:`CellFaults`).

Each fault rides the simulators' own ``fault_hook`` and fires on the k-th event (connect, capture, move)
counted from when it is armed, so the code under test meets it through the real device path. ADR 0033.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

from cellcal.devices.base import Device
from cellcal.devices.errors import CellcalError, DeviceConnectionError, DeviceTimeoutError
from cellcal.devices.pose import Pose
from cellcal.sims.arm import SimArm
from cellcal.sims.camera_shell import SimCameraShell
from cellcal.sims.world import SimWorld

__all__ = ["MAX_STALL_S", "CellFaults", "FaultableCell"]

#: Longest stall a fault may inject, seconds (a bound, so a mistaken test cannot hang for ever).
MAX_STALL_S = 600.0
#: The camera turned to face away from the scene: half a turn about its own x axis.
_LOOK_AWAY = Pose.from_xyz_rpy([0.0, 0.0, 0.0], [math.pi, 0.0, 0.0])


class FaultableCell(Protocol):
    """What :class:`CellFaults` needs of a cell (:class:`~cellcal.testing.sim.SimCell` is one).

    The cell owns its faults, so the faults see it through this protocol rather than
    importing the cell's module (which imports this one).
    """

    @property
    def camera(self) -> Device:
        """The camera as the configuration builds it (its ``backend_name`` decides which faults apply)."""
        ...

    @property
    def arm(self) -> Device:
        """The arm as the configuration builds it."""
        ...

    @property
    def sim_camera(self) -> SimCameraShell:
        """The simulated camera behind :attr:`camera` (carries the ``fault_hook``)."""
        ...

    @property
    def sim_arm(self) -> SimArm | None:
        """The simulated arm behind :attr:`arm`; None when it runs in another process."""
        ...

    @property
    def world(self) -> SimWorld:
        """The simulated world both devices share."""
        ...


@dataclass(eq=False)  # identity: two equal faults are two faults
class _Armed:
    name: str
    device: str  # "camera" | "arm"
    event: str  # "connect" | "capture" | "move"
    armed_at: int  # events of this kind seen when the fault was armed
    first: int  # the event number (as this object counts) the fault fires on first
    count: int  # how many consecutive events it affects
    action: Callable[[int], None]  # called with the event's number counted from arming
    fired: int = 0


class CellFaults:
    """Faults armed on a :class:`~cellcal.testing.sim.SimCell`'s simulated devices.

    ``k`` counts events from when the fault is armed: ``capture=1`` is the next capture, ``move=2``
    the move after next; ``count`` consecutive events are affected (default one). What the code
    under test then sees:

    ============================ ==================================================================
    fault                        the call that meets it
    ============================ ==================================================================
    :meth:`camera_timeout`       ``capture`` raises :class:`DeviceTimeoutError` (``sim`` camera)
    :meth:`camera_disconnect`    ``capture`` raises :class:`DeviceConnectionError` (``sim`` camera)
    :meth:`camera_connect_fails` ``connect`` raises :class:`DeviceConnectionError` (``sim`` camera)
    :meth:`camera_stall`         ``capture`` blocks ``seconds`` first: on ``o3r-emulated`` the
                                 driver's capture times out (:class:`DeviceTimeoutError`); on
                                 ``sim`` the call overruns its timeout, which a
                                 :class:`~cellcal.core.calibration.Calibrator` ends with
                                 :class:`~cellcal.devices.errors.BackendOverrunError`
    :meth:`blank_frame`          the frame arrives with no valid pixel (the camera saw nothing in
                                 range); a calibration refuses it (``CalibrationQualityError``)
    :meth:`arm_stall`            the motion stops progressing: ``move_linear`` raises
                                 :class:`DeviceTimeoutError` at its motion timeout
    :meth:`arm_error`            the controller latches an error (default 31, a protective stop):
                                 ``move_linear`` raises :class:`~cellcal.devices.errors.VendorError`
    :meth:`arm_disconnect`       ``move_linear`` raises :class:`DeviceConnectionError` as the
                                 motion starts (``sim`` arm)
    :meth:`arm_connect_fails`    ``connect`` raises :class:`DeviceConnectionError` (``sim`` arm)
    ============================ ==================================================================

    Faults that raise need the plain ``sim`` backend (its hook runs on the caller's thread); the
    others work behind the emulated backends too. Behind ``o3r-emulated`` a capture event is a
    frame the emulator renders (a free-running head renders more frames than are captured; the
    default ``trigger = "software"`` renders one per capture). :meth:`clear` disarms everything
    and undoes a blank frame still in effect; :attr:`fired` says how often each fault has fired.
    """

    def __init__(self, cell: FaultableCell) -> None:
        self._cell = cell
        self._lock = threading.Lock()
        self._armed: list[_Armed] = []
        self._true_mount: Pose | None = None
        #: Events seen by this object's hooks, per (device, event): a faulted call that raises is
        #: not counted by the simulator itself, so faults count on their own.
        self._seen: dict[tuple[str, str], int] = {}
        self.fired: dict[str, int] = {}

    # ------------------------------------------------------------------ camera
    def camera_timeout(self, capture: int = 1, count: int = 1) -> None:
        """The ``capture``-th capture from now raises :class:`DeviceTimeoutError` (no frame came)."""
        self._need_plain("camera_timeout", "camera")

        def act(n: int) -> None:
            raise DeviceTimeoutError(f"sim camera: no frame within the timeout (injected fault, capture {n})")
        self._arm("camera_timeout", "camera", "capture", capture, count, act)

    def camera_disconnect(self, capture: int = 1, count: int = 1) -> None:
        """The ``capture``-th capture from now raises :class:`DeviceConnectionError` (the camera dropped off)."""
        self._need_plain("camera_disconnect", "camera")

        def act(n: int) -> None:
            raise DeviceConnectionError(f"sim camera: connection lost (injected fault, capture {n})")
        self._arm("camera_disconnect", "camera", "capture", capture, count, act)

    def camera_connect_fails(self, connect: int = 1, count: int = 1) -> None:
        """The ``connect``-th connect from now raises :class:`DeviceConnectionError` (nobody answers)."""
        self._need_plain("camera_connect_fails", "camera")

        def act(n: int) -> None:
            raise DeviceConnectionError(f"sim camera: connection refused (injected fault, connect {n})")
        self._arm("camera_connect_fails", "camera", "connect", connect, count, act)

    def camera_stall(self, seconds: float, capture: int = 1, count: int = 1) -> None:
        """The ``capture``-th capture from now is held ``seconds`` before its frame is rendered.

        Args:
            seconds: How long the frame is held, s (0 < seconds <= :data:`MAX_STALL_S`).
        """
        if not 0.0 < seconds <= MAX_STALL_S:
            raise CellcalError(f"camera_stall: seconds must be within (0, {MAX_STALL_S:g}] s, got {seconds!r}")
        self._arm("camera_stall", "camera", "capture", capture, count, lambda _n: time.sleep(seconds))

    def blank_frame(self, capture: int = 1, count: int = 1) -> None:
        """The ``capture``-th frame from now (and ``count - 1`` after it) has no valid pixel.

        The simulated camera faces away from the scene for those frames (its true mount turned
        half a turn about its x axis), so the frame is rendered and delivered as usual, empty.
        """
        world = self._cell.world

        def act(_n: int) -> None:
            if self._true_mount is None:
                self._true_mount = world.mount
                world.mount = world.mount @ _LOOK_AWAY
        self._arm("blank_frame", "camera", "capture", capture, count, act)

    # ------------------------------------------------------------------ arm
    def arm_stall(self, move: int = 1, count: int = 1) -> None:
        """The ``move``-th motion from now stops progressing; ``move_linear`` times out."""
        arm = self._sim_arm("arm_stall")
        self._arm("arm_stall", "arm", "move", move, count, lambda _n: arm.freeze_motion())

    def arm_error(self, code: int = 31, move: int = 1) -> None:
        """The controller latches error ``code`` as the ``move``-th motion from now starts (31: protective stop).

        The error stays until the arm's errors are cleared (``arm.clear_errors()``).
        """
        arm = self._sim_arm("arm_error")
        if not 0 < int(code) < 1 << 16:
            raise CellcalError(f"arm_error: code must be within [1, 65535], got {code!r}")
        self._arm("arm_error", "arm", "move", move, 1, lambda _n: arm.set_error(int(code)))

    def arm_disconnect(self, move: int = 1, count: int = 1) -> None:
        """The ``move``-th motion from now raises :class:`DeviceConnectionError` as it starts."""
        self._need_plain("arm_disconnect", "arm")

        def act(n: int) -> None:
            raise DeviceConnectionError(f"sim arm: connection lost (injected fault, move {n})")
        self._arm("arm_disconnect", "arm", "move", move, count, act)

    def arm_connect_fails(self, connect: int = 1, count: int = 1) -> None:
        """The ``connect``-th connect of the arm from now raises :class:`DeviceConnectionError`."""
        self._need_plain("arm_connect_fails", "arm")

        def act(n: int) -> None:
            raise DeviceConnectionError(f"sim arm: connection refused (injected fault, connect {n})")
        self._arm("arm_connect_fails", "arm", "connect", connect, count, act)

    # ------------------------------------------------------------------ housekeeping
    def clear(self) -> None:
        """Disarm every fault and give the camera its true mount back (after a blank frame)."""
        with self._lock:
            self._armed.clear()
            self._restore_mount()
        self._cell.sim_camera.fault_hook = None
        if self._cell.sim_arm is not None:
            self._cell.sim_arm.fault_hook = None

    def _restore_mount(self) -> None:
        if self._true_mount is not None:
            self._cell.world.mount = self._true_mount
            self._true_mount = None

    def _need_plain(self, fault: str, device: str) -> None:
        backend = self._cell.camera.backend_name if device == "camera" else self._cell.arm.backend_name
        if backend != "sim":
            raise CellcalError(f"{fault} needs the 'sim' {device} backend (its fault is raised on the caller's "
                               f"thread); this cell's {device} is {backend!r}")

    def _sim_arm(self, fault: str) -> SimArm:
        arm = self._cell.sim_arm
        if arm is None:
            raise CellcalError(f"{fault}: the arm backend {self._cell.arm.backend_name!r} runs its simulator in "
                               "another process; use the emulator's own faults")
        return arm

    def _arm(self, name: str, device: str, event: str, k: int, count: int, action: Callable[[int], None]) -> None:
        if isinstance(k, bool) or not isinstance(k, int) or k < 1:
            raise CellcalError(f"{name}: the {event} number must be an integer >= 1, got {k!r}")
        if isinstance(count, bool) or not isinstance(count, int) or count < 1:
            raise CellcalError(f"{name}: count must be an integer >= 1, got {count!r}")
        with self._lock:
            seen = self._seen.get((device, event), 0)
            self._armed.append(_Armed(name, device, event, seen, seen + k, count, action))
            self.fired.setdefault(name, 0)
        if device == "camera":
            self._cell.sim_camera.fault_hook = self._camera_hook
        else:
            self._sim_arm(name).fault_hook = self._arm_hook

    def _camera_hook(self, event: str, n: int) -> None:
        if event == "capture":
            with self._lock:
                self._restore_mount()  # a blank frame lasts one capture
        self._fire("camera", event, n)

    def _arm_hook(self, event: str, n: int) -> None:
        self._fire("arm", event, n)

    def _fire(self, device: str, event: str, _sim_n: int) -> None:
        with self._lock:
            n = self._seen[(device, event)] = self._seen.get((device, event), 0) + 1
            due = [a for a in self._armed
                   if a.device == device and a.event == event and a.first <= n < a.first + a.count]
            for a in due:
                a.fired += 1
                self.fired[a.name] += 1
            self._armed = [a for a in self._armed if not (a in due and n >= a.first + a.count - 1)]
        for a in due:
            a.action(n - a.armed_at)

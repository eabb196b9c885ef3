"""The fake OAK of test_oak.py, streaming, for the worker process of an isolated OAK camera (and for this one).

:func:`make_camera` is the ``worker_factory`` of test_oak_isolated.py's camera: imported by name in
the worker (the test puts this folder and tests/support on PYTHONPATH), it replaces depthai's
``Device`` and ``Pipeline`` there with :class:`StreamingOak` and builds the in-process
:class:`~cellcal.drivers.oak.camera.OakCamera`. Each read of the depth queue sends the next frame,
its depth a function of its sequence number only, so two runs give bit-identical frames. With
``$CELLCAL_TEST_OAK_DIR/stall`` present the queue sends nothing and ``get`` first creates
``$CELLCAL_TEST_OAK_DIR/waiting``: a capture then waits in the worker until the test kills it.
"""

from __future__ import annotations

import datetime
import itertools
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any
from unittest import mock

import numpy as np
import test_oak
from _vendor_autospec import strict_autospec
from test_oak import dai

from cellcal.drivers.oak.camera import OakCamera, OakConfig


def depth_of(seq: int) -> np.ndarray:
    """The depth image of frame ``seq``: 0.3..4 m in millimetres, some pixels invalid (0)."""
    rng = np.random.default_rng(seq)
    depth = rng.integers(300, 4000, size=(test_oak.H, test_oak.W)).astype(np.uint16)
    depth[rng.random(depth.shape) < 0.05] = 0
    return depth


def _control() -> Path | None:
    where = os.environ.get("CELLCAL_TEST_OAK_DIR")
    return Path(where) if where else None


class StreamingQueue(dai.MessageQueue):  # type: ignore[misc]
    """The real host queue; the "device" sends the next frame on every read (unless stalled)."""

    def __init__(self, name: str, max_size: int, blocking: bool) -> None:
        super().__init__(name, max_size, blocking)
        self.seq = itertools.count(1)

    def _stalled(self) -> bool:
        control = _control()
        return control is not None and (control / "stall").exists()

    def tryGetAll(self) -> list[Any]:  # noqa: N802 - depthai's name
        if not self._stalled():
            seq = next(self.seq)
            self.send(test_oak.depth_message(depth_of(seq), seq))
        return list(super().tryGetAll())

    def get(self, timeout: datetime.timedelta) -> Any:
        control = _control()
        if self._stalled() and control is not None:
            (control / "waiting").touch()
        return super().get(timeout)


class StreamingOak(test_oak.FakeOak):
    """A fresh streaming depth queue per pipeline, so one fake serves many connect/close cycles."""

    def output(self) -> Any:
        out = strict_autospec(dai.Node.Output)
        out.createOutputQueue.side_effect = lambda maxSize=16, blocking=False: StreamingQueue(
            "depth", maxSize, blocking)
        return out


def patch_depthai(patch_object: Callable[..., Any]) -> StreamingOak:
    """Make depthai open a :class:`StreamingOak` (``patch_object`` as ``mocker.patch.object``)."""
    fake = StreamingOak()
    patch_object(dai, "Device", side_effect=fake.open)
    patch_object(dai, "Pipeline", side_effect=fake.make_pipeline)
    return fake


def make_camera(config: OakConfig) -> OakCamera:
    """In the worker: depthai patched for good (the process is the camera's), the in-process OAK camera."""
    patch_depthai(lambda *args, **kwargs: mock.patch.object(*args, **kwargs).start())
    return OakCamera(config)

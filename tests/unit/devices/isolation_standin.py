"""A camera "SDK" stand-in for test_isolation_frames.py, imported by name in the worker process.

:class:`StandInCamera` makes frames from its sequence number only (so two runs give the same
frames); a capture whose timeout is below :data:`SLOW_BELOW_S` ignores it and takes
:data:`SLOW_S`, as a misbehaving SDK would (the parent's deadline has to end the wait).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from cellcal.devices.base import BackendContext
from cellcal.devices.isolation.camera import IsolatableCamera
from cellcal.devices.types import DeviceInfo, Frame, Intrinsics

SLOW_BELOW_S = 0.2
SLOW_S = 1.5


@dataclass(frozen=True)
class StandInConfig:
    width: int = 32
    height: int = 24
    isolate: bool = True


class StandInCamera(IsolatableCamera):
    backend_name = "stand-in"
    Config = StandInConfig
    native_library = "stand-in-sdk"
    worker_factory = "isolation_standin:StandInCamera"

    def __init__(self, config: StandInConfig, context: BackendContext | None = None) -> None:
        super().__init__()
        self.config = config
        self._seq = 0
        self._intr = Intrinsics(config.width, config.height, 40.0, 41.0, config.width / 2, config.height / 2,
                                k1=0.01)

    def _connect(self, timeout: float) -> None:
        if self.config.isolate:
            self._start_worker("stand-in", timeout, 2.0)

    def _close(self) -> None:
        self._stop_worker()

    def _info(self) -> DeviceInfo:
        if self._worker is not None:
            return self._worker.info()
        return DeviceInfo(backend="stand-in", vendor="none", model="m", extra={"nested": {"a": [1, [2, [3]]]}})

    def _intrinsics(self) -> Intrinsics:
        return self._worker.intrinsics() if self._worker is not None else self._intr

    def _capture(self, timeout: float) -> Frame:
        if self._worker is not None:
            return self._worker.capture(timeout)
        if timeout < SLOW_BELOW_S:
            time.sleep(SLOW_S)
        self._seq += 1
        h, w = self.config.height, self.config.width
        rng = np.random.default_rng(self._seq)
        distance = rng.uniform(0.3, 2.0, (h, w)).astype(np.float32)
        valid = rng.random((h, w)) > 0.1
        distance[~valid] = np.nan
        xyz = rng.standard_normal((h, w, 3)).astype(np.float32)
        xyz[~valid] = np.nan
        return Frame(distance=distance, xyz=xyz, amplitude=rng.random((h, w), dtype=np.float32), valid=valid,
                     intrinsics=self._intr, timestamp=1.7e9 + self._seq / 30, sequence=self._seq,
                     confidence=rng.integers(0, 2**16, (h, w)).astype(np.uint16),
                     metadata={"pair": (1, 2.5), "words": ["a", {"b": None}]})

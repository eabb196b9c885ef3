"""Where the emulator's frames come from: one source capture per frame, or one render per arm pose.

* :class:`PerFrame` captures the source once per frame sent (a simulated camera's random
  stream and clock advance exactly as if it were captured directly: deterministic).
* :class:`PerPose` captures the (noise-free) source once per camera pose and adds fresh
  Gaussian range noise to the distance counts of every frame, with the data-sheet sigma
  of each pixel's distance: a random window of a precomputed bank of standard normal
  draws, scaled per pixel, written straight into the reused wire image. This is what
  lets the emulator serve load rates (ADR 0024).
"""

from __future__ import annotations

from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from cellcal.devices.types import Frame, Intrinsics

from ..tof import datasheet_sigma_m
from .encoder import FrameCounts, FrameEncoder

#: Standard normal draws kept for the per-frame noise (8 MiB of float32).
NOISE_BANK = 1 << 21


class FrameSource(Protocol):
    """What the emulator renders from (any :class:`Camera3D` qualifies)."""

    @property
    def intrinsics(self) -> Intrinsics: ...

    def capture(self, timeout: float | None = None) -> Frame: ...


class PerFrame:
    """One ``source.capture`` per frame.

    Args:
        source: The frame source.
        encoder: The encoder whose quantisation is used.
        timeout_s: Timeout of each capture, s.
    """

    def __init__(self, source: FrameSource, encoder: FrameEncoder, timeout_s: float) -> None:
        self.source = source
        self.encoder = encoder
        self.timeout_s = timeout_s
        self.captures = 0

    def next(self) -> tuple[FrameCounts, float]:
        """The next frame's wire images and its source timestamp (epoch s)."""
        frame = self.source.capture(self.timeout_s)
        self.captures += 1
        return self.encoder.counts(frame), float(frame.timestamp)


class PerPose:
    """One ``source.capture`` per camera pose, fresh range noise per frame.

    The pose is read from ``source.world.camera_pose()`` when the source has a world (a
    ``SimCamera``); a source without one is treated as static.

    Args:
        source: The frame source; it should be noise-free (the noise is added here).
        encoder: The encoder whose quantisation is used.
        timeout_s: Timeout of each capture, s.
        noise_scale: Multiplier of the data-sheet sigma (0: noise-free).
        seed: Seed of the noise.
    """

    def __init__(self, source: FrameSource, encoder: FrameEncoder, timeout_s: float, *,
                 noise_scale: float = 1.0, seed: int = 0) -> None:
        self.source = source
        self.encoder = encoder
        self.timeout_s = timeout_s
        self.noise_scale = noise_scale
        self.captures = 0
        self._rng = np.random.default_rng(seed)
        self._bank = self._rng.standard_normal(NOISE_BANK, dtype=np.float32)
        self._key: bytes | None = None
        self._base: NDArray[np.float32] | None = None
        self._sigma: NDArray[np.float32] | None = None
        self._out: FrameCounts | None = None
        self._scratch: NDArray[np.float32] | None = None
        self._timestamp = 0.0

    def _pose_key(self) -> bytes:
        world: Any = getattr(self.source, "world", None)
        if world is None or not hasattr(world, "camera_pose"):
            return b"static"
        return bytes(np.asarray(world.camera_pose().as_matrix(), dtype=np.float64).tobytes())

    def _render(self) -> None:
        """Capture the pose's frame and precompute its counts and per-pixel noise sigma (in counts)."""
        frame = self.source.capture(self.timeout_s)
        self.captures += 1
        counts = self.encoder.counts(frame)
        res = float(np.float32(self.encoder.distance_resolution_m))
        base = counts.distance.astype(np.float32)
        # data-sheet sigma of each pixel's distance, in counts; none where there is no measurement
        sigma = (datasheet_sigma_m(base * res, 1.0, self.noise_scale) / res).astype(np.float32)
        # keep every draw inside 0..65535 (6 sigma), and invalid pixels at 0
        sigma = np.minimum(sigma, np.minimum(base, 65535.0 - base) / 6.0).astype(np.float32)
        sigma[counts.distance == 0] = 0.0
        self._base, self._sigma = base.ravel(), sigma.ravel()
        self._out = FrameCounts(counts.distance.copy(), counts.amplitude, counts.confidence)
        self._scratch = np.empty(base.size, np.float32)
        self._timestamp = float(frame.timestamp)

    def next(self) -> tuple[FrameCounts, float]:
        """The next frame's wire images (reused arrays, valid until the next call) and the pose's timestamp."""
        key = self._pose_key()
        if key != self._key or self._out is None:
            self._render()
            self._key = key
        assert self._base is not None and self._sigma is not None and self._out is not None
        assert self._scratch is not None
        n = self._base.size
        # fresh noise: a random window of the bank, scaled per pixel, added to the noise-free counts
        start = int(self._rng.integers(0, NOISE_BANK - n))
        np.multiply(self._bank[start:start + n], self._sigma, out=self._scratch)
        self._scratch += self._base
        np.rint(self._scratch, out=self._scratch)
        np.copyto(self._out.distance.reshape(-1), self._scratch, casting="unsafe")
        return self._out, self._timestamp

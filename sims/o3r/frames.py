"""Where the emulator's frames come from: one source capture per frame, or one render per arm pose.

* :class:`PerFrame` captures the source once per frame sent (a simulated camera's random
  stream and clock advance exactly as if it were captured directly: deterministic).
* :class:`PerPose` captures the (noise-free) source once per camera pose and adds fresh
  Gaussian range noise to the distance counts of every frame, with the data-sheet sigma
  of each pixel's distance. A frame's noise is the sum of two halves (:class:`NoiseHalves`),
  each of variance sigma^2 / 2, taken from two banks of 64 per-pose noisy images drawn
  from a bank of standard normal draws; the 4096 pairs are visited in a shuffled order,
  so no two frames within 4096 are equal and each frame costs one uint16 addition.
  The pose is checked by the identity of what the world composes it from; the
  amplitude and confidence images are handed out read-only (the encoder copies them
  once per pose). This is what lets the emulator serve load rates (ADR 0024, ADR 0052).
* :class:`OffsetView` is a further head's source: a simulated camera rendering the same
  world from the first head's pose moved by a fixed offset.
"""

from __future__ import annotations

import random
import threading
from typing import Any, Protocol, cast

import numpy as np
from numpy.typing import NDArray

from cellcal.devices.pose import Pose
from cellcal.devices.types import Frame, Intrinsics

from ..tof import datasheet_sigma_m
from .encoder import FrameCounts, FrameEncoder
from .wire import DEFAULT_CHUNKS

#: Standard normal draws kept for the per-frame noise (8 MiB of float32), clipped to +-NOISE_CLIP.
NOISE_BANK = 1 << 21
#: Largest draw of the bank, in sigmas of a half.
NOISE_CLIP = 6.0
#: Noisy images per half-bank: 64 x 64 = 4096 distinct frames per pose (2 x 64 x 77 KB at 224 x 172).
NOISE_HALVES = 64


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

    def next(self, chunks: tuple[int, ...] = DEFAULT_CHUNKS) -> tuple[FrameCounts, float]:
        """The next frame's wire images and its source timestamp (epoch s); ``chunks`` is not used."""
        frame = self.source.capture(self.timeout_s)
        self.captures += 1
        return self.encoder.counts(frame), float(frame.timestamp)


class _PoseRenderer(Protocol):
    """A simulated camera that renders its world from any pose (``SimCamera``)."""

    @property
    def intrinsics(self) -> Intrinsics: ...

    @property
    def world(self) -> Any: ...

    def render(self, camera_pose: Pose, *, timestamp: float | None = None, sequence: int = 0) -> Frame: ...


class OffsetView:
    """A further head of the emulated VPU: a simulated camera rendering the world from the first head's pose
    moved by a fixed offset, ``T_base_head = T_base_camera @ offset``.

    ``T_base_camera`` is the world's camera pose (``world.camera_pose()``) when the frame is
    rendered, so the head moves with the first head (one rig on the flange, or both fixed).
    Noise, timestamps (the simulated clock) and every artefact are the camera's own; the
    clock is not advanced here (the first head's captures pace it). ``world`` is exposed so
    that :class:`PerPose` renders once per pose.

    Args:
        camera: The simulated camera of this head (e.g. ``SimCamera(config, world=first.world)``).
        offset: ``T_camera_head``: the head's optical frame in the first head's optical frame (m, rad).
    """

    def __init__(self, camera: _PoseRenderer, offset: Pose) -> None:
        self.camera = camera
        self.offset = offset
        self.sequence = 0
        self._lock = threading.Lock()

    @property
    def intrinsics(self) -> Intrinsics:
        """The camera's intrinsics."""
        return self.camera.intrinsics

    @property
    def world(self) -> Any:
        """The simulated world the camera renders."""
        return self.camera.world

    def pose(self) -> Pose:
        """The head's pose in the base frame now, ``T_base_head``."""
        return cast(Pose, self.camera.world.camera_pose() @ self.offset)

    def capture(self, timeout: float | None = None) -> Frame:
        """Render the next frame from :meth:`pose` (``timeout`` is not used: rendering does not wait)."""
        with self._lock:
            self.sequence += 1
            return self.camera.render(self.pose(), sequence=self.sequence)


class NoiseHalves:
    """Per-frame distance counts ``A[i] + B[j]``: two banks of half-noise images, filled on first use.

    ``A[i]`` is ``round(base + sigma / sqrt(2) * z)`` and ``B[j]`` is ``round(sigma / sqrt(2) * z')``
    (int16 held as uint16: the uint16 sum wraps to the right count), each ``z`` a window
    of standard normal draws at a start drawn per pose; ``sigma`` is capped so that the
    sum stays in 0..65535. The pairs ``(i, j)`` come in a shuffled order of all
    ``halves**2``, reshuffled when used up (never repeating the last pair first).

    Args:
        bank: Standard normal draws, clipped to +-:data:`NOISE_CLIP`.
        draws: Source of the window starts and the pair order.
        halves: Images per bank.
    """

    def __init__(self, bank: NDArray[np.float32], draws: random.Random, halves: int = NOISE_HALVES) -> None:
        self.bank = bank
        self.draws = draws
        self.halves = halves
        self._order: list[int] = []
        self._last = -1
        self._base = np.zeros(0, np.float32)
        self._sigma = np.zeros(0, np.float32)
        self._images = np.zeros((2 * halves, 0), np.uint16)
        self._filled = [False] * (2 * halves)
        self._starts: list[int] = []

    def reset(self, base: NDArray[np.uint16], sigma: NDArray[np.float32]) -> None:
        """A new pose: noise-free counts ``base`` and per-pixel sigma (counts, 0 where no measurement)."""
        n = base.size
        self._base = base.reshape(-1).astype(np.float32)
        # each half: sigma / sqrt(2), capped so that two halves of NOISE_CLIP draws, each rounded, stay in 0..65535
        room = np.maximum(np.minimum(self._base, 65535.0 - self._base) - 1.0, 0.0) / (2.0 * NOISE_CLIP)
        self._sigma = np.minimum(sigma.reshape(-1) / np.float32(np.sqrt(2.0)), room).astype(np.float32)
        if self._images.shape[1] != n:
            self._images = np.empty((2 * self.halves, n), np.uint16)
        self._filled = [False] * (2 * self.halves)
        self._starts = [self.draws.randrange(self.bank.size - n + 1) for _ in range(2 * self.halves)]

    def _image(self, k: int) -> NDArray[np.uint16]:
        """Half-image ``k`` (0..halves-1: A, with the base; the rest: B, noise only), drawn on first use."""
        image: NDArray[np.uint16] = self._images[k]
        if not self._filled[k]:
            n = image.size
            noise = self.bank[self._starts[k]:self._starts[k] + n] * self._sigma
            if k < self.halves:
                noise += self._base
            np.rint(noise, out=noise)
            np.copyto(image, noise.astype(np.int16 if k >= self.halves else np.uint16).view(np.uint16))
            self._filled[k] = True
        return image

    def _pair(self) -> int:
        if not self._order:
            self._order = list(range(self.halves * self.halves))
            self.draws.shuffle(self._order)
            if self._order[-1] == self._last:  # popped from the end: never the pair just used
                self._order[0], self._order[-1] = self._order[-1], self._order[0]
        self._last = self._order.pop()
        return self._last

    def add_into(self, out: NDArray[np.uint16]) -> None:
        """Write the next frame's distance counts into ``out`` (the base's shape)."""
        i, j = divmod(self._pair(), self.halves)
        np.add(self._image(i), self._image(self.halves + j), out=out.reshape(-1))


class PerPose:
    """One ``source.capture`` per camera pose, fresh range noise per frame (:class:`NoiseHalves`).

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
        bank = np.random.default_rng(seed).standard_normal(NOISE_BANK, dtype=np.float32)
        self._noise = NoiseHalves(np.clip(bank, -NOISE_CLIP, NOISE_CLIP, out=bank), random.Random(seed))
        self._inputs: tuple[object, ...] | None = None
        self._key: bytes | None = None
        self._out: FrameCounts | None = None
        self._wired: FrameCounts | None = None  # _out with the distance in the encoder's buffer
        self._timestamp = 0.0

    def _pose_key(self) -> bytes:
        world: Any = getattr(self.source, "world", None)
        if world is None or not hasattr(world, "camera_pose"):
            return b"static"
        return bytes(np.asarray(world.camera_pose().as_matrix(), dtype=np.float64).tobytes())

    def _pose_inputs(self) -> tuple[object, ...] | None:
        """The objects a ``SimWorld`` composes the camera pose from (flange pose, fixed camera pose, mount).

        Poses are immutable and the arm hands out the same flange pose while it stands,
        so while every one of them is the same object the camera has not moved (they are
        held here, so no identity is reused). None for a source whose world is not made so.
        """
        world: Any = getattr(self.source, "world", None)
        arm = getattr(world, "arm", None)
        if arm is None or not hasattr(world, "apply_events") or not hasattr(world, "mount"):
            return None
        world.apply_events()  # as camera_pose() does: a mount event's time may have come
        return (arm.flange_pose(), getattr(world, "camera_flange", None), world.mount)

    def _moved(self) -> bool:
        """Whether the camera pose differs from the rendered one (by identity alone while it stands)."""
        inputs, seen = self._pose_inputs(), self._inputs
        if (self._out is not None and inputs is not None and seen is not None
                and inputs[0] is seen[0] and inputs[1] is seen[1] and inputs[2] is seen[2]):
            return False
        self._inputs = inputs
        key = self._pose_key()
        if key == self._key and self._out is not None:
            return False
        self._key = key
        return True

    def _render(self) -> None:
        """Capture the pose's frame and precompute its counts and per-pixel noise sigma (in counts)."""
        frame = self.source.capture(self.timeout_s)
        self.captures += 1
        counts = self.encoder.counts(frame)
        res = float(np.float32(self.encoder.distance_resolution_m))
        # data-sheet sigma of each pixel's distance, in counts; none where there is no measurement
        sigma = (datasheet_sigma_m(counts.distance * res, 1.0, self.noise_scale) / res).astype(np.float32)
        sigma[counts.distance == 0] = 0.0
        self._noise.reset(counts.distance, sigma)
        amplitude, confidence = counts.amplitude.copy(), counts.confidence.copy()
        amplitude.flags.writeable = confidence.flags.writeable = False  # fixed for the pose: copied once
        self._out = FrameCounts(counts.distance.copy(), amplitude, confidence)
        self._timestamp = float(frame.timestamp)

    def next(self, chunks: tuple[int, ...] = DEFAULT_CHUNKS) -> tuple[FrameCounts, float]:
        """The next frame's wire images (reused arrays, valid until the next call) and the pose's timestamp.

        Args:
            chunks: The chunk selection encoded first: when it carries the distance, the
                distance is written straight into that message buffer (the encoder then
                finds it there and does not copy it).
        """
        if self._moved():
            self._render()
        out = self._out
        assert out is not None
        h, w = out.distance.shape
        view = self.encoder.layout(chunks, w, h).views.get(100)
        if view is None:
            self._noise.add_into(out.distance)
            return out, self._timestamp
        if self._wired is None or self._wired.distance is not view or self._wired.amplitude is not out.amplitude:
            self._wired = FrameCounts(cast("NDArray[np.uint16]", view), out.amplitude, out.confidence)
        self._noise.add_into(self._wired.distance)
        return self._wired, self._timestamp

"""The O3R emulator's load-rate path (issue #38): per-pose frames with noise from two half-banks, and an
encoder that reuses its buffer, writes a read-only image once and the TOF_INFO's steady fields once."""

from __future__ import annotations

import itertools
import random
from collections.abc import Iterator

import numpy as np
import pytest

from cellcal.devices.base import BackendContext
from cellcal.devices.pose import Pose
from cellcal.sims.camera import SimCamera, SimCameraConfig
from cellcal.sims.o3r.encoder import FrameCounts, FrameEncoder
from cellcal.sims.o3r.frames import NOISE_CLIP, NoiseHalves, PerPose
from cellcal.sims.o3r.wire import models_from_intrinsics


@pytest.fixture
def sim() -> Iterator[SimCamera]:
    cam = SimCamera(SimCameraConfig(noise=False, distortion=False), BackendContext(seed=4)).connect()
    yield cam
    cam.close()


def halves(seed: int = 1, k: int = 8) -> NoiseHalves:
    bank = np.random.default_rng(seed).standard_normal(1 << 16, dtype=np.float32)
    return NoiseHalves(np.clip(bank, -NOISE_CLIP, NOISE_CLIP, out=bank), random.Random(seed), halves=k)


def test_noise_halves_have_the_per_pixel_sigma_around_the_base() -> None:
    base = np.full((30, 40), 20000, np.uint16)
    base[:, 20:] = 5000
    base[0, 0] = 0  # no measurement: stays 0
    sigma = np.where(base > 10000, 40.0, 10.0).astype(np.float32)
    sigma[0, 0] = 0.0
    noise = halves(k=32)
    noise.reset(base, sigma)
    out = np.empty_like(base)
    frames = []
    for _ in range(1024):  # one full cycle of the 32 x 32 pairs
        noise.add_into(out)
        frames.append(out.astype(np.float64))
    d = np.stack(frames) - base
    assert np.all(d[:, 0, 0] == 0)
    # each region's 29 x 20 pixels x 32 draws per half: the sd is within 5 % of sigma (its sampling error is
    # ~0.5 %) and the mean within 5 of its standard errors (0.29 and 0.07 counts) of the base
    wide, narrow = d[:, 1:, :20], d[:, 1:, 20:]
    assert abs(float(wide.std()) / 40.0 - 1) < 0.05 and abs(float(narrow.std()) / 10.0 - 1) < 0.05
    assert abs(float(wide.mean())) < 1.5 and abs(float(narrow.mean())) < 0.4
    # frames that share no half are uncorrelated: the first 32 pairs of a cycle (i, j) are mostly distinct
    flat = d[:, 1:, :20].reshape(len(frames), -1)
    r = np.corrcoef(flat[:64])
    assert float(np.median(np.abs(r[np.triu_indices(64, 1)]))) < 0.1


def test_noise_halves_never_repeat_a_frame_within_a_cycle_nor_across_its_end() -> None:
    base = np.full((6, 8), 30000, np.uint16)
    noise = halves(k=4)
    noise.reset(base, np.full(base.shape, 50.0, np.float32))
    out = np.empty_like(base)
    seen = []
    for _ in range(3 * 16):  # three cycles of the 16 pairs
        noise.add_into(out)
        seen.append(out.tobytes())
    for cycle in range(3):
        assert len(set(seen[16 * cycle:16 * (cycle + 1)])) == 16
    assert all(a != b for a, b in itertools.pairwise(seen))


def test_noise_halves_stay_inside_the_16_bit_counts() -> None:
    base = np.array([[1, 2, 3, 65533, 65534, 65535, 40]], np.uint16)
    noise = halves(k=16)
    noise.reset(base, np.full(base.shape, 5000.0, np.float32))  # far wider than the room to either end
    out = np.empty_like(base)
    values = []
    for _ in range(256):
        noise.add_into(out)
        values.append(out[0].astype(np.int64))
    v = np.stack(values)
    low, high = v[:, :3], v[:, 3:6]
    assert low.min() >= 0 and low.max() <= 6 and high.min() >= 65529  # a wrap would land near the other end
    assert v[:, 6].std() > 1.0  # 40 counts from 0: it moves, inside its room of 39


@pytest.mark.parametrize("mode", ["cyclic_4m_2m_4m_2m", "standard_range2m"])
def test_encoder_buffer_equals_a_fresh_encode_whatever_came_before(sim: SimCamera, mode: str) -> None:
    models = models_from_intrinsics(sim.intrinsics)
    enc = FrameEncoder(models, mode=mode)
    counts = enc.counts(sim.capture(1.0))
    steady = [counts.amplitude.copy(), counts.confidence.copy()]
    for image in steady:
        image.flags.writeable = False
    other = counts.amplitude.copy() + 7
    other.flags.writeable = False
    rng = np.random.default_rng(0)
    for n, (amplitude, extrinsic) in enumerate([(steady[0], (0.0,) * 6), (steady[0], (0.0,) * 6),
                                                (other, (0.0,) * 6), (steady[0], (0.01, 0, 0, 0, 0, 0.2)),
                                                (counts.amplitude, (0.01, 0, 0, 0, 0, 0.2))], start=1):
        distance = (counts.distance.astype(np.int64) + rng.integers(-3, 4, counts.distance.shape)).clip(0, 65535)
        frame = FrameCounts(distance.astype(np.uint16), amplitude, steady[1])
        enc.extrinsic_optic_to_user = extrinsic
        got = bytes(enc.encode(frame, n, 1_700_000_000_123_456_789 + n))
        fresh = FrameEncoder(models, mode=mode, extrinsic_optic_to_user=extrinsic)
        assert got == bytes(fresh.encode(frame, n, 1_700_000_000_123_456_789 + n)), f"frame {n}"


def test_encoder_v1_headers_and_a_chunk_subset_equal_a_fresh_encode(sim: SimCamera) -> None:
    models = models_from_intrinsics(sim.intrinsics)
    counts = FrameEncoder(models).counts(sim.capture(1.0))
    for version in (1, 2, 3):
        enc = FrameEncoder(models, header_version=version, confidence_bits=8)
        for n in (1, 2):
            for chunks in ((300, 100), (100, 101, 300, 420), [420, 101]):
                got = bytes(enc.encode(counts, n, 5_000_000_123 * n, chunks))
                fresh = FrameEncoder(models, header_version=version, confidence_bits=8)
                assert got == bytes(fresh.encode(counts, n, 5_000_000_123 * n, chunks)), (version, n, chunks)


def test_per_pose_renders_again_when_the_mount_or_the_flange_moves_and_not_otherwise(sim: SimCamera) -> None:
    frames = PerPose(sim, FrameEncoder(models_from_intrinsics(sim.intrinsics)), 1.0)
    first = frames.next()[0].distance.copy()
    frames.next()
    assert frames.captures == 1
    arm = sim.world.arm
    arm.set_flange_pose(Pose(arm.flange_pose().rotation, arm.flange_pose().translation))  # same pose, new object
    frames.next()
    assert frames.captures == 1
    sim.world.bump_mount(Pose.from_xyz_rotvec([0.0, 0.0, 0.02], [0.0, 0.0, 0.0]))  # 20 mm along the view
    moved = frames.next()[0].distance
    assert frames.captures == 2
    ok = (first > 0) & (moved > 0)
    shift_m = float(np.median(moved[ok].astype(np.float64) - first[ok])) * (10.0 / 65535.0)
    assert -0.025 < shift_m < -0.015  # the plane 20 mm nearer along the axis (noise ~ 2 mm per pixel)
    arm.set_flange_pose(Pose.from_xyz_rotvec([0.0, 0.0, 0.01], [0.0, 0.0, 0.0]) @ arm.flange_pose())
    frames.next()
    assert frames.captures == 3

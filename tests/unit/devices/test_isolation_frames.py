"""Camera frames from a worker process through a shared-memory ring (ADR 0063): the ring, its layout and
header, its slots after an overrun, its segment never left behind, and cellcal's errors crossing the pipe
as themselves. The camera is isolation_standin.py's stand-in, imported by name in the worker."""

from __future__ import annotations

import os
import pickle
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from isolation_standin import SLOW_S, StandInCamera, StandInConfig

from cellcal.devices.errors import ConfigError, DeviceError, DeviceTimeoutError, ProtocolError, VendorError
from cellcal.devices.isolation import NativeHost
from cellcal.devices.isolation import protocol as p
from cellcal.devices.isolation.frames import MAX_RING_BYTES, FrameRing, header, layout, write

HERE = Path(__file__).parent
SHM = Path("/dev/shm")
ARRAYS = ("distance", "xyz", "amplitude", "valid", "confidence")


@pytest.fixture
def on_path(monkeypatch: pytest.MonkeyPatch) -> None:
    """The worker finds isolation_standin.py."""
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([str(HERE), os.environ.get("PYTHONPATH", "")]))


@pytest.fixture
def pair(on_path: None) -> Iterator[tuple[StandInCamera, StandInCamera]]:
    """The stand-in in a worker and in this process, connected."""
    isolated, here = StandInCamera(StandInConfig()), StandInCamera(StandInConfig(isolate=False))
    with isolated.connect(timeout=20.0), here.connect(timeout=1.0):
        yield isolated, here


def _same(a: object, b: object) -> None:
    for name in ARRAYS:
        x, y = getattr(a, name), getattr(b, name)
        assert x.dtype == y.dtype and x.shape == y.shape and x.tobytes() == y.tobytes(), name


# ---------------------------------------------------------------- the ring itself
def test_a_frame_written_into_a_slot_reads_back_bit_for_bit() -> None:
    frame = StandInCamera(StandInConfig(isolate=False)).connect(1.0).capture(1.0)
    entries, nbytes = layout(frame)
    assert [e[0] for e in entries] == list(ARRAYS) and all(e[3] % 64 == 0 for e in entries)
    assert nbytes >= sum(getattr(frame, n).nbytes for n in ARRAYS)
    ring = FrameRing(nbytes, 2)
    try:
        write(ring._map.buf, ring.slot_bytes, frame, entries)          # slot 1
        back = ring.read(1, entries, header(frame))
    finally:
        ring.close()
    _same(back, frame)
    assert (back.intrinsics, back.timestamp, back.sequence) == (frame.intrinsics, frame.timestamp, frame.sequence)
    assert back.metadata == {"pair": (1, 2.5), "words": ["a", {"b": None}]}   # tuples stay tuples
    assert not (SHM / ring.name).exists()
    ring.close()                                                         # twice: nothing


def test_a_header_naming_any_class_and_a_layout_outside_the_slot_are_refused() -> None:
    frame = StandInCamera(StandInConfig(isolate=False)).connect(1.0).capture(1.0)
    entries, nbytes = layout(frame)
    ring = FrameRing(nbytes, 1)
    try:
        bad = pickle.dumps({"intrinsics": {}, "metadata": np.float64(1.0)})   # numpy: a class to import
        with pytest.raises(ProtocolError, match="only builtin values travel"):
            ring.read(0, entries, bad)
        name, dtype, shape, _ = entries[1]
        with pytest.raises(ProtocolError, match=r"layout puts xyz <f4 \(24, 32, 3\) at byte"):
            ring.read(0, [(name, dtype, shape, ring.slot_bytes - 64)], header(frame))
        with pytest.raises(ProtocolError, match="layout puts"):
            ring.read(0, [("distance", "|O", (2,), 0)], header(frame))      # no objects from shared memory
        with pytest.raises(ProtocolError, match="wrote slot 1 of a ring of 1"):
            ring.read(1, entries, header(frame))
    finally:
        ring.close()


def test_slots_of_overrun_calls_stay_out_of_use_until_the_worker_answers_again() -> None:
    ring = FrameRing(1024, 3)
    try:
        first = ring.acquire()
        ring.abandon(first)                      # its call overran: the worker may still write it
        second = ring.acquire()
        ring.abandon(second)
        third = ring.acquire()
        assert len({first, second, third}) == 3
        with pytest.raises(DeviceError, match="every slot of the frame ring is held"):
            ring.acquire()
        ring.release(third)                      # an answer: the worker finished the earlier calls too
        assert sorted(ring.acquire() for _ in range(3)) == [0, 1, 2]
    finally:
        ring.close()


def test_a_ring_is_bounded() -> None:
    with pytest.raises(DeviceError, match=f"over the {MAX_RING_BYTES} allowed"):
        FrameRing(MAX_RING_BYTES // 2, 3)
    with pytest.raises(ValueError, match=r"1\.\.8 slots"):
        FrameRing(1024, 9)


def test_the_worker_maps_the_segment_without_unlinking_it_when_it_ends() -> None:
    # SharedMemory(name) in the worker would register the segment with the worker's resource tracker, which
    # unlinks it when the worker ends: the parent's segment would vanish under it
    ring = FrameRing(4096, 2)
    host = NativeHost("test", library="none", backend="test")
    host.start(10.0)
    try:
        mapping = host.module("cellcal.devices.isolation.frames").Mapping(ring.name, ring.slot_bytes * 2)
        mapping.close()
    finally:
        host.close(2.0)
    try:
        assert (SHM / ring.name).exists()
    finally:
        ring.close()
    assert not (SHM / ring.name).exists()


# ---------------------------------------------------------------- a camera in the worker
def test_frames_identity_and_intrinsics_cross_unchanged(pair: tuple[StandInCamera, StandInCamera]) -> None:
    isolated, here = pair
    for _ in range(5):                           # more frames than slots
        a, b = isolated.capture(1.0), here.capture(1.0)
        _same(a, b)
        assert (a.sequence, a.timestamp, a.metadata) == (b.sequence, b.timestamp, b.metadata)
    assert isolated.intrinsics == here.intrinsics and isolated.info() == here.info()
    assert isolated.info().extra == {"nested": {"a": [1, [2, [3]]]}}   # deeper than a plain reply may be


def test_an_overrun_capture_is_a_timeout_and_the_next_one_gets_its_own_frame(
        pair: tuple[StandInCamera, StandInCamera]) -> None:
    isolated, here = pair
    with pytest.raises(DeviceTimeoutError, match=r"capture\(timeout=0.1 s\).* did not finish within 0.6 s"):
        isolated.capture(0.1)                     # the stand-in ignores it and takes SLOW_S
    assert SLOW_S > 0.6
    here.capture(0.1)                             # the same frame in this process (sequence 1), discarded
    _same(isolated.capture(5.0), here.capture(5.0))   # waits for the late one; its reply is skipped
    _same(isolated.capture(5.0), here.capture(5.0))


def test_cellcal_errors_cross_the_pipe_as_themselves(on_path: None) -> None:
    host = NativeHost("test", library="none", backend="test")
    host.start(10.0)
    try:
        run = host.module("builtins").exec
        with pytest.raises(VendorError) as vendor:
            run("from cellcal.devices.errors import VendorError; raise VendorError('o3r-ifm3d', 7, 'busy')", {})
        assert (type(vendor.value), vendor.value.code, str(vendor.value)) == (VendorError, 7, "o3r-ifm3d error 7: busy")
        with pytest.raises(ConfigError) as config:
            run("from cellcal.devices.errors import ConfigError; raise ConfigError('no port', key='camera.port')", {})
        assert config.value.key == "camera.port" and str(config.value) == "key 'camera.port': no port"
        with pytest.raises(ProtocolError) as protocol:
            run("from cellcal.devices.errors import ProtocolError; raise ProtocolError('short', offset=12)", {})
        assert protocol.value.offset == 12
    finally:
        host.close(2.0)
    assert p.rebuild_error("NoSuchError", "m", ("m",), {}).args == ("NoSuchError: m",)   # unknown: as before


def test_a_frame_wraps_its_slot_while_another_stays_free_and_gives_it_back_when_gone(
        pair: tuple[StandInCamera, StandInCamera]) -> None:
    isolated, here = pair
    kept = [isolated.capture(1.0) for _ in range(5)]
    expected = [here.capture(1.0) for _ in range(5)]
    ring = isolated._worker._ring  # type: ignore[union-attr]
    assert ring is not None and ring.slots == 3
    # the first two hold their slots (views); with one slot left the others are copies
    assert [f.xyz.flags.owndata for f in kept] == [False, False, True, True, True]
    assert (ring.leased, ring.free) == (2, 1)
    for got, want in zip(kept, expected, strict=True):
        _same(got, want)                              # later captures did not write over a held frame
    del kept[0], got
    assert (ring.leased, ring.free) == (1, 2)         # the slot came back with the frame's last array
    assert not isolated.capture(1.0).xyz.flags.owndata
    name = ring.name
    isolated.close()                                  # a held frame keeps its memory, the segment goes
    assert not (SHM / name).exists()
    _same(kept[0], expected[1])

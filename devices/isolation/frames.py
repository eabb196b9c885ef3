"""Camera frames from a worker process through shared memory: :class:`FrameRing` and the slot layout.

The parent owns the memory: one ``multiprocessing.shared_memory`` segment holding a few
slots, each sized for one frame of the stream (its arrays, 64-byte aligned). The worker maps
it by name and writes a frame into the slot the parent names; only the slot's index, the
arrays' layout and the frame's scalars (a pickled header of builtin values) cross the pipe.
The parent wraps the slot (the frame's arrays are views of it, and the slot comes back when
the last of them is gone) while another slot stays free for the next capture, else copies the
arrays out and frees the slot at once. The parent unlinks the segment when the camera closes
and when the worker dies, so no segment outlives its camera (a wrapped frame keeps its memory
mapped, nameless, until it is gone; Python's resource tracker unlinks the segment if the
parent itself is killed).
"""

from __future__ import annotations

import contextlib
import ctypes
import io
import mmap
import os
import pickle
import secrets
import threading
import weakref
from dataclasses import fields
from multiprocessing import shared_memory
from typing import Any, cast

import numpy as np

from ..errors import DeviceError, ProtocolError
from ..measurement import MeasurementModel
from ..types import Frame, Intrinsics

#: Slots of a ring: a few, so that a capture that overran its deadline (its worker still writing) does not
#: hold up the next one.
DEFAULT_SLOTS = 3
MAX_SLOTS = 8
#: Largest ring, bytes (all slots): 64 MiB holds 3 frames of 1280 x 800 with every array.
MAX_RING_BYTES = 64 << 20
#: Alignment of each array inside a slot, bytes.
ALIGN = 64
#: A frame's arrays in slot order; ``confidence`` only when the frame has one.
ARRAYS = ("distance", "xyz", "amplitude", "valid", "confidence")

#: One array of a slot: (name, numpy dtype string, shape, byte offset in the slot).
Entry = tuple[str, str, tuple[int, ...], int]


def _aligned(n: int) -> int:
    return (n + ALIGN - 1) // ALIGN * ALIGN


def layout(frame: Frame) -> tuple[list[Entry], int]:
    """Where each array of ``frame`` goes in a slot, and the bytes the slot needs."""
    entries: list[Entry] = []
    offset = 0
    for name in ARRAYS:
        arr = getattr(frame, name)
        if arr is None:
            continue
        entries.append((name, arr.dtype.str, tuple(int(n) for n in arr.shape), offset))
        offset = _aligned(offset + arr.nbytes)
    return entries, offset


def write(buf: Any, base: int, frame: Frame, entries: list[Entry]) -> None:
    """Copy ``frame``'s arrays into ``buf`` (a mapped slot starting at byte ``base``) as ``entries`` say."""
    for name, dtype, shape, offset in entries:
        view: np.ndarray[Any, Any] = np.ndarray(shape, np.dtype(dtype), buffer=buf, offset=base + offset)
        np.copyto(view, getattr(frame, name), casting="no")


def fields_of(obj: Any) -> dict[str, Any]:
    """A dataclass's fields, one level deep (``dataclasses.asdict`` deep-copies: ~1 ms a frame)."""
    return {f.name: getattr(obj, f.name) for f in fields(obj)}


def header(frame: Frame) -> bytes:
    """The frame's scalars, pickled from builtin values only (the parent refuses anything else)."""
    return pickle.dumps({"intrinsics": fields_of(frame.intrinsics), "timestamp": float(frame.timestamp),
                         "sequence": int(frame.sequence), "metadata": frame.metadata,
                         "measurement": fields_of(frame.measurement)}, protocol=pickle.HIGHEST_PROTOCOL)


class _BuiltinsOnly(pickle.Unpickler):
    """An unpickler that builds containers and scalars only: no class is looked up, nothing is imported."""

    def find_class(self, module: str, name: str) -> Any:
        raise pickle.UnpicklingError(f"the worker's frame header names {module}.{name}; only builtin values travel")


def loads_builtins(data: bytes) -> Any:
    """Unpickle ``data`` holding only builtin values (dicts, lists, tuples, scalars)."""
    return _BuiltinsOnly(io.BytesIO(data)).load()


class FrameRing:
    """The parent's shared-memory ring: ``slots`` slots of ``slot_bytes`` each, owned and unlinked here.

    Args:
        slot_bytes: Bytes of one slot (one frame of the stream, every array).
        slots: How many slots (``1..MAX_SLOTS``).

    Raises:
        DeviceError: If the ring would exceed :data:`MAX_RING_BYTES` or the memory cannot be had.
    """

    def __init__(self, slot_bytes: int, slots: int = DEFAULT_SLOTS) -> None:
        if not 1 <= slots <= MAX_SLOTS:
            raise ValueError(f"a frame ring has 1..{MAX_SLOTS} slots, not {slots}")
        self.slot_bytes = _aligned(max(1, int(slot_bytes)))
        self.slots = slots
        if self.slot_bytes * slots > MAX_RING_BYTES:
            raise DeviceError(f"frames of {self.slot_bytes} bytes need a ring of {self.slot_bytes * slots} bytes, "
                              f"over the {MAX_RING_BYTES} allowed")
        name = f"cellcal_{os.getpid()}_{secrets.token_hex(4)}"
        try:
            # made (and registered with Python's resource tracker) by SharedMemory, kept for the unlink
            self._shm = shared_memory.SharedMemory(name, create=True, size=self.slot_bytes * slots)
            # mapped as the worker maps it: an mmap that outlives close() while a wrapped frame holds it
            # (SharedMemory.close() would fail then, and again in its __del__)
            self._map: Mapping | None = Mapping(self._shm.name, self.slot_bytes * slots, handle=self._shm)
        except OSError as exc:
            raise DeviceError(f"cannot create a shared-memory ring of {self.slot_bytes * slots} bytes: {exc}") from None
        self.name = self._shm.name
        self._lock = threading.Lock()
        self._free = list(range(slots))
        #: Slots handed to calls that overran: the worker may still write them; free once it answers again.
        self._late: list[int] = []
        #: Slots wrapped by frames still alive (they come back when the frame's arrays are gone).
        self.leased = 0
        self._unlinked = False

    @property
    def closed(self) -> bool:
        """Whether the segment is gone (unlinked; frames that wrap it keep their memory)."""
        return self._unlinked

    @property
    def free(self) -> int:
        """Slots free now."""
        return len(self._free)

    def acquire(self) -> int:
        """A free slot's index.

        Raises:
            DeviceError: If every slot is held by a call the worker has not answered or a frame still alive.
        """
        with self._lock:
            if not self._free:
                raise DeviceError(f"every slot of the frame ring is held by captures the worker has not answered "
                                  f"or frames still alive ({self.slots} slots, {self.leased} held by frames)")
            return self._free.pop(0)

    def release(self, slot: int | None) -> None:
        """Give ``slot`` back (None: none); the worker answered, so the slots of earlier overrun calls are free too."""
        with self._lock:
            self._free.extend([*self._late, *(() if slot is None else (slot,))])
            self._late.clear()

    def abandon(self, slot: int) -> None:
        """``slot``'s call overran: keep the slot out of use until the worker answers a later call."""
        with self._lock:
            self._late.append(slot)

    def _returned(self, slot: int) -> None:
        """The last array of a wrapped frame is gone (any thread): its slot is free again."""
        with self._lock:
            self.leased -= 1
            if not self._unlinked:
                self._free.append(slot)

    def read(self, slot: int, entries: list[Entry], head: bytes, *, wrap: bool = False) -> Frame:
        """The frame the worker wrote into ``slot`` (``entries`` as :func:`layout` gave them).

        Args:
            slot: The slot.
            entries: Its arrays' layout.
            head: Its pickled scalars (:func:`header`).
            wrap: The arrays are views of the slot, which is held until they are gone; else copies
                (the caller frees the slot).

        Raises:
            ProtocolError: If the layout or the header does not describe a frame inside the slot.
        """
        assert self._map is not None and not self._unlinked
        if not 0 <= slot < self.slots:
            raise ProtocolError(f"the worker wrote slot {slot} of a ring of {self.slots}")
        try:
            scalars = loads_builtins(head)
            intrinsics = Intrinsics(**scalars["intrinsics"])
            measurement = MeasurementModel(**scalars["measurement"])
        except (pickle.UnpicklingError, KeyError, TypeError, ValueError, EOFError) as exc:
            raise ProtocolError(f"the worker's frame header is unreadable: {exc}") from None
        arrays: dict[str, Any] = {}
        # the lease: a ctypes view of the slot every array refers to; when the last array goes, it goes
        lease = (ctypes.c_char * self.slot_bytes).from_buffer(self._map.buf, slot * self.slot_bytes)
        for name, dtype, shape, offset in entries:
            dt = np.dtype(dtype)
            count = int(np.prod(shape, dtype=np.int64))
            if name not in ARRAYS or dt.hasobject or offset < 0 or offset + dt.itemsize * count > self.slot_bytes:
                raise ProtocolError(f"the worker's frame layout puts {name} {dtype} {shape} at byte {offset} of a "
                                    f"{self.slot_bytes}-byte slot")
            view = np.frombuffer(cast(Any, lease), dt, count, offset).reshape(shape)
            arrays[name] = view if wrap else view.copy()
        try:
            frame = Frame(intrinsics=intrinsics, timestamp=scalars["timestamp"], sequence=scalars["sequence"],
                          metadata=scalars["metadata"], measurement=measurement, **arrays)
        except (KeyError, TypeError, ValueError) as exc:  # FrameError is a ValueError
            raise ProtocolError(f"the worker's frame does not hold together: {exc}") from None
        if wrap:  # only now: a frame refused above leaves its slot to the caller
            with self._lock:
                self.leased += 1
            weakref.finalize(lease, self._returned, slot)
        return frame

    def close(self) -> None:
        """Unlink the segment and unmap it (a wrapped frame keeps its memory till it goes); never raises."""
        with self._lock:
            if self._unlinked:
                return
            self._unlinked = True
            with contextlib.suppress(FileNotFoundError, OSError):
                self._shm.unlink()
            mapping, self._map = self._map, None
            if mapping is not None:
                mapping.close()


class Mapping:
    """A view of a ring's segment (the worker's, and the parent's): :attr:`buf`, :meth:`close` to unmap.

    Args:
        name: The segment.
        size: Its size, bytes.
        handle: The parent's own ``SharedMemory`` of it: on POSIX it is closed (the segment stays,
            mapped here); elsewhere its buffer is used.
    """

    def __init__(self, name: str, size: int, handle: shared_memory.SharedMemory | None = None) -> None:
        self._shm: shared_memory.SharedMemory | None = None
        self._mmap: mmap.mmap | None = None
        if handle is not None and os.name != "posix":  # Windows: the segment lives while a handle is open
            self._shm = handle
            self.buf: Any = handle.buf
            return
        if handle is not None:
            handle.close()  # its name stays, for unlink()
        if os.name == "posix":
            # SharedMemory(name) would register the segment with a resource tracker (Python < 3.13), whose
            # exit with the worker would unlink the parent's segment: mapped here directly instead
            import _posixshmem  # the module SharedMemory itself uses on POSIX

            fd = _posixshmem.shm_open("/" + name, os.O_RDWR, mode=0o600)
            try:
                self._mmap = mmap.mmap(fd, size)
            finally:
                os.close(fd)
            self.buf = self._mmap
        else:  # Windows: a named mapping, no tracker
            self._shm = shared_memory.SharedMemory(name)
            self.buf = self._shm.buf

    def close(self) -> None:
        """Unmap (the parent unlinks); while a wrapped frame holds the memory, that frame unmaps it. Never raises."""
        self.buf = None
        with contextlib.suppress(BufferError, ValueError, OSError):
            if self._mmap is not None:
                self._mmap.close()
            if self._shm is not None:
                self._shm.close()

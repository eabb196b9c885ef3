"""Shared set-up of the fault, resume and dry-run tests: small fast cells and device probes."""

from __future__ import annotations

import copy
import signal
import threading
import time
import tomllib
from collections.abc import Iterator
from dataclasses import dataclass, field
from importlib import resources
from typing import Any

from leaks import open_fds

from cellcal.core.calibration.calibrator import Calibrator, build_devices
from cellcal.core.calibration.config import parse_config
from cellcal.sims.arm import SimArm
from cellcal.sims.camera import SimCamera
from cellcal.sims.o3r.backend import EmulatedO3RCamera
from cellcal.sims.o3r.emulator import O3REmulator
from cellcal.sims.xarm.backend import EmulatedXArmArm
from cellcal.sims.xarm.emulator import XArmEmulator

SIM_DOC = tomllib.loads(resources.files("cellcal.configs").joinpath("sim.toml").read_text())

#: Timeouts of the test cells, seconds (short, so a stall costs little).
CAPTURE_TIMEOUT_S = 0.5
MOVE_TIMEOUT_S = 0.5
O3R_IO_TIMEOUT_S = 2.0  # > capture timeout: a stalled frame ends as the capture's timeout
XARM_REPLY_TIMEOUT_S = 0.1
XARM_RETRIES = 1


def cell_document(camera: str = "sim", arm: str = "sim", **tables: dict[str, Any]) -> dict[str, Any]:
    """The packaged sim cell, made fast (one perimeter, one method), with the given backends."""
    doc = copy.deepcopy(SIM_DOC)
    doc["plan"].update(perimeters_px=[20], methods=["plane_fit"], capture_timeout_s=CAPTURE_TIMEOUT_S,
                       move_timeout_s=MOVE_TIMEOUT_S)
    doc["camera"] = {"backend": camera}
    if camera == "o3r-emulated":
        doc["camera"].update(trigger="software", io_timeout_s=O3R_IO_TIMEOUT_S)
    doc["arm"] = {"backend": arm, "time_scale": 0.001}
    if arm == "xarm-emulated":
        doc["arm"].update(axes=5, reply_timeout_s=XARM_REPLY_TIMEOUT_S, retries=XARM_RETRIES, poll_interval_s=0.005)
    for table, values in tables.items():
        doc.setdefault(table, {}).update(values)
    return doc


@dataclass
class Probe:
    """The simulated devices behind a calibrator, and the emulators once they start."""

    calibrator: Calibrator
    sim_arm: SimArm
    sim_camera: SimCamera
    xarm: list[XArmEmulator] = field(default_factory=list)
    o3r: list[O3REmulator] = field(default_factory=list)


def make_probe(doc: dict[str, Any], source: str = "<fault-cell>") -> Probe:
    """Build a calibrator for ``doc`` and find the simulated devices behind its backends."""
    config = parse_config(doc, source)
    camera, arm = build_devices(config)
    inner = arm.inner
    sim_arm = inner.sim_arm if isinstance(inner, EmulatedXArmArm) else inner
    sim_camera = camera.sim if isinstance(camera, EmulatedO3RCamera) else camera
    assert isinstance(sim_arm, SimArm) and isinstance(sim_camera, SimCamera)
    probe = Probe(Calibrator(config, camera, arm), sim_arm, sim_camera)
    if isinstance(inner, EmulatedXArmArm):
        inner.on_emulator_started = probe.xarm.append
    if isinstance(camera, EmulatedO3RCamera):
        camera.on_emulator_started = probe.o3r.append
    return probe


def interrupt() -> None:
    """Deliver SIGINT to this process now (Python turns it into KeyboardInterrupt in the main thread)."""
    assert threading.current_thread() is threading.main_thread()
    signal.raise_signal(signal.SIGINT)
    time.sleep(1.0)  # not reached: the handler raises before this returns


def leftovers(threads_before: set[threading.Thread], fds_before: set[tuple[str, str]],
              settle_s: float = 1.0) -> tuple[list[threading.Thread], set[tuple[str, str]]]:
    """Threads and descriptors opened since the snapshot and still open (after up to ``settle_s``)."""
    deadline = time.monotonic() + settle_s
    while True:
        threads = [t for t in threading.enumerate() if t not in threads_before and t.is_alive()]
        fds = open_fds() - fds_before
        if (not threads and not fds) or time.monotonic() >= deadline:
            return threads, fds
        time.sleep(0.02)


def all_threads() -> set[threading.Thread]:
    return set(threading.enumerate())


def iter_rows(result: dict[str, Any]) -> Iterator[dict[str, Any]]:
    for pose in result["poses"]:
        yield from pose["measurements"]

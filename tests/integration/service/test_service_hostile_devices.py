"""A camera's native worker killed mid-capture under the service (issue #41, hostile devices; ADR 0063).

The cell: the packaged sim cell whose camera is ``o3r-ifm3d`` (ifm3dpy in its worker process, the
default), talking to cellcal's O3R emulator, which serves the simulated camera of the sim arm's own
world (software trigger: one rendered frame per capture). The emulator runs in this process (the
service's): ifm3dpy holds the GIL, but in its worker, not here. A calibrate run is started over
HTTP; at its second pose the emulator holds the frame back (the simulated camera's fault hook), so
the worker waits in ``capture``; the test SIGKILLs the worker there (its pid from the camera
object the builder keeps: ``worker_pid``). Then: the run ends ``failed`` with the crash's one line
(also as a ``run.state`` server-sent event), the arm was told to stop and started no move after
the crash nor any twice, the service answers, the next run starts a new worker and ends ``ok``,
and the history keeps both runs.

The same with the ``oak`` backend (depthai in its worker): the streaming fake of
tests/unit/drivers/oak installed in the worker. Its frames are random depths, not a scene the arm
looks at, so a run over it cannot calibrate: there the second run shows a new worker measuring,
and ends on the measurement (not on a crash).
"""

from __future__ import annotations

import importlib
import os
import signal
import threading
import time
from collections.abc import Callable, Iterator
from importlib import resources
from pathlib import Path
from typing import Any

import httpx
import pytest
from conftest import WAIT_S, serving
from test_service_http import CELL, FAST, follow_events, wait_for

from cellcal.core.calibration.build import build_devices
from cellcal.core.service import HistoryStore, Service
from cellcal.devices.base import BackendContext
from cellcal.devices.registry import default_registry

SIM_TOML = resources.files("cellcal.configs").joinpath("sim.toml").read_text()
SHM = Path("/dev/shm")
ENDED = ("ok", "failed", "cancelled")
OAK_TESTS = Path(__file__).parents[2] / "unit" / "drivers" / "oak"


def cell_config(tmp_path: Path, camera: str, plan: dict[str, str] | None = None) -> Path:
    """sim.toml with ``camera`` as its ``[camera]`` table's body (and ``[plan]`` keys replaced)."""
    text = SIM_TOML.replace('[camera]\nbackend = "sim"\n', f"[camera]\n{camera}\n")
    for key, value in (plan or {}).items():
        old = next(line for line in text.splitlines() if line.startswith(f"{key} = "))
        text = text.replace(old, f"{key} = {value}")
    assert camera in text
    path = tmp_path / "cell.toml"
    path.write_text(text)
    return path


class Cell:
    """Builds each run's devices: the configured camera and the sim arm; keeps them and every move's target.

    Args:
        camera: ``(config, sim camera of the arm's world) -> the camera the run drives``.
    """

    def __init__(self, camera: Callable[[Any, Any], Any]) -> None:
        self.camera = camera
        self.cameras: list[Any] = []
        self.arms: list[Any] = []
        self.sims: list[Any] = []
        self.targets: list[list[Any]] = []  # per run, the target of every move the arm was sent
        self.closers: list[Callable[[], None]] = []
        #: The fault hook given to the first run's simulated camera (None: none).
        self.first_hook: Callable[[str, int], None] | None = None

    def __call__(self, config: Any) -> tuple[Any, Any]:
        sim, arm = build_devices(config, camera={"backend": "sim"})  # the sim camera shares the arm's world
        inner, targets = arm.inner, []
        begin = inner.begin_move_linear

        def logged(pose: Any, *args: Any) -> None:
            targets.append(pose)
            begin(pose, *args)

        inner.begin_move_linear = logged
        if not self.sims and self.first_hook is not None:
            sim.fault_hook = self.first_hook
        camera = self.camera(config, sim)
        self.sims.append(sim)
        self.arms.append(inner)
        self.targets.append(targets)
        self.cameras.append(camera)
        return camera, arm

    def close(self) -> None:
        for close in self.closers:
            close()
        for sim in self.sims:
            sim.close()


def _segments() -> set[str]:
    """This process's shared-memory segments (the frame rings' names carry the parent's pid)."""
    return {p.name for p in SHM.iterdir() if p.name.startswith(f"cellcal_{os.getpid()}_")}


def _wait(condition: Callable[[], bool], what: str) -> None:
    end = time.monotonic() + WAIT_S
    while not condition():
        assert time.monotonic() < end, what
        time.sleep(0.01)


def _one_line(text: str) -> str:
    assert "\n" not in text and "Traceback" not in text and 0 < len(text) <= 500
    return text


def _service(tmp_path: Path, config: Path, cell: Cell) -> Service:
    return Service([config], tmp_path / "out", build=cell, history=HistoryStore.beside(tmp_path))


def _killed_run(client: httpx.Client, cell: Cell, waiting: Callable[[], bool]) -> tuple[dict[str, Any], int]:
    """Start a run; once ``waiting()`` (the worker waits in capture) SIGKILL the camera's worker; the ended run."""
    started = client.post(f"{CELL}/runs", json=FAST)
    assert started.status_code == 202, started.text
    run_id = started.json()["id"]
    _wait(lambda: (bool(cell.cameras) and waiting()) or client.get(f"/runs/{run_id}").json()["state"] in ENDED,
          "the capture never waited")
    assert waiting(), f"the run ended before its capture waited: {client.get(f'/runs/{run_id}').json()['error']}"
    pid = cell.cameras[0].worker_pid
    assert pid not in (None, os.getpid())
    os.kill(pid, signal.SIGKILL)
    return wait_for(client, run_id), pid


def _check_after_the_crash(client: httpx.Client, cell: Cell, run: dict[str, Any], moves: int) -> str:
    """The killed run: failed with the crash's line, the arm stopped, ``moves`` moves made, none twice."""
    assert run["state"] == "failed" and run["progress"]["poses_done"] == moves - 1
    error = _one_line(run["error"])
    assert "worker process died during capture" in error and "SIGKILL" in error
    arm = cell.arms[0]
    assert arm.stops >= 1  # the calibrator's failure path told the arm to stop
    assert arm.moves_started == len(cell.targets[0]) == moves  # nothing moved after the crash
    assert len({repr(t.to_dict()) for t in cell.targets[0]}) == moves  # no target was sent twice
    health = client.get("/health")
    assert health.status_code == 200 and health.json()["status"] == "ok" and health.json()["cells"] == {
        "paper-sim": None}
    assert not _segments()  # the frame ring was unlinked at the crash
    return error


def _check_history(client: httpx.Client, service: Service, first: dict[str, Any], error: str,
                   second_state: str) -> None:
    """Both runs in the history, newest first, the killed one with its reason; the events of both kept."""
    runs = client.get("/history/runs").json()["items"]
    assert [r["status"] for r in runs] == [second_state, "failed"]
    assert runs[1]["reason"] == error and runs[1]["kind"] == "calibrate"
    assert service.recorder.flush()
    events = client.get("/history/events", params={"kind": "run.state"}).json()["items"]
    assert [e["detail"]["state"] for e in events] == ["running", "failed", "running", second_state]
    assert events[1]["detail"]["id"] == first["id"] and events[1]["detail"]["error"] == error


def test_a_worker_started_from_a_thread_that_ends_outlives_that_thread() -> None:
    # a run's device calls go through DeadlineGuard threads that end with the call; the worker asks to die with
    # its parent (PR_SET_PDEATHSIG), and Linux means the thread that forked it: the fork is done by a thread that
    # lives as long as the process
    from cellcal.devices.isolation.host import NativeHost

    host = NativeHost("test", library="none", backend="test")
    starter = threading.Thread(target=host.start, args=(WAIT_S,))
    starter.start()
    starter.join(WAIT_S)
    try:
        assert host.pid is not None and host._proc is not None
        time.sleep(0.3)  # a SIGKILL at the thread's end would have come by now
        assert host._proc.poll() is None and host.pid in _children()
        assert host.module("os").getpid() == host.pid  # and it answers
    finally:
        host.close()


# ---------------------------------------------------------------------------------------------- o3r-ifm3d


@pytest.fixture
def o3r_cell() -> Iterator[Cell]:
    pytest.importorskip("ifm3dpy.framegrabber", reason="ifm3dpy (the o3r-ifm3d extra) is not installed")
    from cellcal.sims.o3r.emulator import O3REmulator

    def camera(config: Any, sim: Any) -> Any:
        sim.connect(10.0)
        emulator = O3REmulator(sim, state="IDLE", clock="unix", state_change_s=0.05).start()
        cell.closers.append(emulator.close)
        section = {**config.camera_section, "xmlrpc_port": emulator.xmlrpc_port}
        return default_registry().create_camera(section, BackendContext(section="camera"))

    cell = Cell(camera)
    yield cell
    cell.close()


def test_an_ifm3dpy_worker_killed_mid_capture_fails_the_run_and_the_next_run_calibrates(
        tmp_path: Path, o3r_cell: Cell) -> None:
    config = cell_config(tmp_path, 'backend = "o3r-ifm3d"\nhost = "127.0.0.1"\nxmlrpc_port = 1\n'
                                   'trigger = "software"')  # the port: the emulator's, set by the builder
    holding, release = threading.Event(), threading.Event()

    def hold(event: str, n: int) -> None:  # on the emulator's thread: the frame of the second pose waits
        if event == "capture" and o3r_cell.arms[0].moves_started == 2 and not holding.is_set():
            holding.set()
            release.wait(WAIT_S)

    o3r_cell.first_hook = hold
    service = _service(tmp_path, config, o3r_cell)
    events: list[dict[str, Any]] = []
    stop = threading.Event()
    with serving(service) as base, httpx.Client(base_url=base, timeout=WAIT_S) as client:
        reader = follow_events(base, events, stop)
        _wait(lambda: service.bus.subscribers == 1, "the event stream did not open")
        try:
            first, pid = _killed_run(client, o3r_cell, holding.is_set)
        finally:
            release.set()
        error = _check_after_the_crash(client, o3r_cell, first, moves=2)
        assert error.startswith("o3r-ifm3d 127.0.0.1 port2: the ifm3dpy worker process died during capture")
        second = wait_for(client, client.post(f"{CELL}/runs", json=FAST).json()["id"])
        assert second["state"] == "ok", second["error"]  # connect() started a new worker
        assert second["progress"] == {"poses_done": 3, "poses_total": 3}
        assert o3r_cell.arms[1].moves_started == len(o3r_cell.targets[1]) == 3
        _check_history(client, service, first, error, "ok")
        _wait(lambda: any(e["type"] == "run.state" and e["data"]["state"] == "ok" for e in events),
              "the stream did not show the second run's end")
        stop.set()
        service.bus.publish("test.end")  # wakes the reader so it sees stop
        reader.join(WAIT_S)
    crash = [e for e in events if e["type"] == "run.state" and e["data"]["state"] == "failed"]
    assert len(crash) == 1 and crash[0]["data"]["error"] == error  # the crash as a server-sent event
    assert o3r_cell.cameras[1].worker_pid is None and pid not in _children()  # closed; the killed one reaped


def _children() -> set[int]:
    """Process ids of this process's children."""
    out = set()
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[1]) == os.getpid():
            out.add(int(stat.parent.name))
    return out


# ---------------------------------------------------------------------------------------------- oak (depthai)


@pytest.fixture
def oak_cell(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[Cell]:
    pytest.importorskip("depthai")
    from cellcal.drivers.oak.camera import OakCamera

    class WorkerOak(OakCamera):
        """The OAK backend whose worker opens tests/unit/drivers/oak's streaming fake instead of a device."""

        worker_factory = "oak_in_worker:make_camera"

    support = Path(__file__).parents[2] / "support"
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([str(OAK_TESTS), str(support), os.environ.get("PYTHONPATH", "")]))
    monkeypatch.setenv("CELLCAL_TEST_OAK_DIR", str(tmp_path))
    monkeypatch.syspath_prepend(str(OAK_TESTS))
    monkeypatch.syspath_prepend(str(support))
    fake = importlib.import_module("test_oak")  # its device id and image size

    def camera(config: Any, sim: Any) -> Any:
        return WorkerOak.from_config({"backend": "oak", "device_id": fake.DEVICE_ID, "width": fake.W,
                                      "height": fake.H, "amplitude": "none"})

    yield Cell(camera)


def test_a_depthai_worker_killed_mid_capture_fails_the_run_and_the_next_run_starts_a_new_worker(
        tmp_path: Path, oak_cell: Cell) -> None:
    # the fake's image is 64 x 40 px: perimeters that fit it
    config = cell_config(tmp_path, 'backend = "sim"', plan={"perimeters_px": "[4, 6]"})
    (tmp_path / "stall").touch()  # the fake sends no frame: the first pose's capture waits in the worker
    service = _service(tmp_path, config, oak_cell)
    with serving(service) as base, httpx.Client(base_url=base, timeout=WAIT_S) as client:
        first, pid = _killed_run(client, oak_cell, (tmp_path / "waiting").exists)
        error = _check_after_the_crash(client, oak_cell, first, moves=1)
        assert error.startswith("oak ") and "the depthai worker process died during capture" in error
        (tmp_path / "stall").unlink()
        second = wait_for(client, client.post(f"{CELL}/runs", json=FAST).json()["id"])
        # random depths are no plane: the run ends on its measurement, having connected a new worker and moved
        assert second["state"] == "failed" and "quality gate" in _one_line(second["error"]), second["error"]
        assert "worker process died" not in second["error"]
        assert oak_cell.arms[1].moves_started >= 1 and oak_cell.cameras[1] is not oak_cell.cameras[0]
        _check_history(client, service, first, error, "failed")
    assert pid not in _children() and not _segments()

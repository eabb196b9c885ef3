"""The service on the simulated cell: a real uvicorn on 127.0.0.1 (port 0) in a thread, and the sim arms it drove."""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from importlib import resources
from pathlib import Path
from typing import Any

import pytest

pytest.importorskip("fastapi")
pytest.importorskip("httpx")

from cellcal.core.calibration.calibrator import build_devices
from cellcal.core.service import Service
from cellcal.core.service.http import create_app

SIM_TOML = resources.files("cellcal.configs").joinpath("sim.toml").read_text()
#: Seconds to wait for a run of the sim cell (a few s each) or for the server to start.
WAIT_S = 120.0


def sim_config(tmp_path: Path, settle_s: float = 0.0, name: str = "sim.toml") -> Path:
    """The packaged sim.toml, with ``settle_s`` seconds of rest at each pose (a slow run to cancel)."""
    text = SIM_TOML.replace("settle_s = 0.0", f"settle_s = {settle_s}")
    assert f"settle_s = {settle_s}" in text
    path = tmp_path / name
    path.write_text(text)
    return path


class Arms:
    """A device builder that keeps every sim arm the service built (to count its moves and stops)."""

    def __init__(self) -> None:
        self.built: list[Any] = []

    def __call__(self, config: Any) -> tuple[Any, Any]:
        camera, arm = build_devices(config)
        self.built.append(arm.inner)  # the SimArm behind the safety wrapper
        return camera, arm


@contextmanager
def serving(service: Service, **options: Any) -> Iterator[str]:
    """Serve ``service`` with uvicorn on 127.0.0.1, any free port, in a thread; yields the base URL (``.../v1``)."""
    import uvicorn

    config = uvicorn.Config(create_app(service, **options), host="127.0.0.1", port=0, log_level="warning",
                            access_log=False, lifespan="on", timeout_graceful_shutdown=2)
    server = uvicorn.Server(config)
    thread = threading.Thread(target=server.run, name="uvicorn-test", daemon=True)
    thread.start()
    ready = threading.Event()
    for _ in range(int(WAIT_S / 0.02)):
        if server.started:
            ready.set()
            break
        ready.wait(0.02)
    assert server.started, "uvicorn did not start"
    port = server.servers[0].sockets[0].getsockname()[1]
    try:
        yield f"http://127.0.0.1:{port}/v1"
    finally:
        server.should_exit = True
        thread.join(WAIT_S)
        service.close()


@pytest.fixture
def arms() -> Arms:
    return Arms()


@pytest.fixture
def make_service(tmp_path: Path, arms: Arms) -> Callable[..., Service]:
    def make(settle_s: float = 0.0) -> Service:
        return Service([sim_config(tmp_path, settle_s)], tmp_path / "out", build=arms)

    return make

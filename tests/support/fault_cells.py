"""Shared set-up of the fault, resume, dry-run and process tests: small fast cells, device probes, cellcal processes."""

from __future__ import annotations

import copy
import re
import signal
import subprocess
import sys
import threading
import time
import tomllib
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
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
MOVE_TIMEOUT_S = 1.5  # a move of the fast cell takes milliseconds; a frozen one ends here
O3R_IO_TIMEOUT_S = 2.0  # > capture timeout: a stalled frame ends as the capture's timeout
XARM_REPLY_TIMEOUT_S = 0.3  # far above a reply's scheduling delay on a busy machine
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
    """Deliver SIGINT to this process now, as Ctrl-C would (Python turns it into KeyboardInterrupt).

    A test process started with SIGINT ignored (a background job, some CI runners) would drop
    the signal, and one with the OS default would die: for the delivery, Python's own handler
    is installed then. When Python's handler is in place and no KeyboardInterrupt arrives,
    this fails loudly instead of letting the run go on. (A handler of the code under test that
    holds the signal for later, like the recorder's, is left in charge.)
    """
    assert threading.current_thread() is threading.main_thread()
    current = signal.getsignal(signal.SIGINT)
    python_handler = current in (signal.SIG_IGN, signal.SIG_DFL, None, signal.default_int_handler)
    previous = signal.signal(signal.SIGINT, signal.default_int_handler) if python_handler else None
    try:
        signal.raise_signal(signal.SIGINT)  # the handler runs before this call returns
    finally:
        if previous is not None:
            signal.signal(signal.SIGINT, previous)
    if python_handler:
        raise AssertionError("SIGINT was delivered but no KeyboardInterrupt arrived")


def leftovers(threads_before: set[threading.Thread], fds_before: set[tuple[str, str]],
              settle_s: float = 30.0) -> tuple[list[threading.Thread], set[tuple[str, str]]]:
    """Threads and descriptors opened since the snapshot and still open (after up to ``settle_s``: what ends
    does so in milliseconds, later only on a loaded machine)."""
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


# ---------------------------------------------------------------------- real cellcal processes


def cellcal_argv() -> list[str]:
    """The ``cellcal`` console script of this environment (``python -m cellcal.core.cli`` without one)."""
    exe = Path(sys.executable).with_name("cellcal")
    return [str(exe)] if exe.exists() else [sys.executable, "-m", "cellcal.core.cli"]


#: What :class:`CellcalProcess` writes on stderr just before it calls ``main`` (``announce=True``).
READY = "cellcal-test: calling main\n"
#: The console script, with :data:`READY` written between importing ``main`` and calling it. SIGINT is
#: held back (blocked) from before the line until main has installed its handler, so a Ctrl-C sent as
#: soon as the line appears lands in main, not in the interpreter's default handler a few bytecodes
#: earlier (a traceback no test of cellcal's own code can prevent).
_ANNOUNCING_SCRIPT = f"""\
import signal, sys
import cellcal.core.cli as cli
install = cli._install
def _install_then_unblock(handler):
    previous = install(handler)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {{signal.SIGINT}})
    return previous
cli._install = _install_then_unblock
signal.pthread_sigmask(signal.SIG_BLOCK, {{signal.SIGINT}})
sys.stderr.write({READY!r}); sys.stderr.flush()
sys.exit(cli.main())
"""


def slow_cell_document(settle_s: float = 0.4, **tables: dict[str, Any]) -> dict[str, Any]:
    """The fast sim cell of :func:`cell_document`, with ``settle_s`` of waiting at each of its 3 poses.

    A run then lasts about ``3 * settle_s`` after start-up, long enough to act on it
    while it runs (the progress bar says which pose it is at).
    """
    doc = cell_document(**tables)
    doc["plan"]["settle_s"] = settle_s
    return doc


class CellcalProcess:
    """A ``cellcal`` subprocess whose stdout and stderr are collected as they come.

    Args:
        args: The arguments after ``cellcal``.
        preexec_fn: Run in the child before it execs (e.g. a resource limit).
        announce: Run the console script's two lines with :data:`READY` on stderr right
            before ``main()`` is called, so a test can act at a known moment however long
            the interpreter takes to start on a loaded machine (:meth:`wait_ready`); the
            line is left out of :meth:`finish`'s stderr.
    """

    def __init__(self, args: list[str], *, preexec_fn: Callable[[], None] | None = None,
                 announce: bool = False) -> None:
        argv = [sys.executable, "-c", _ANNOUNCING_SCRIPT, *args] if announce else [*cellcal_argv(), *args]
        self.proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, preexec_fn=preexec_fn)
        self._out = bytearray()
        self._err = bytearray()
        self._readers = [threading.Thread(target=self._drain, args=(stream, buf), daemon=True)
                         for stream, buf in ((self.proc.stdout, self._out), (self.proc.stderr, self._err))]
        for reader in self._readers:
            reader.start()

    def __enter__(self) -> CellcalProcess:
        return self

    def __exit__(self, *exc: object) -> None:
        """A process still running when the test leaves (a failed assertion) is killed and reaped."""
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(5.0)
        for reader in self._readers:
            reader.join(5.0)

    @staticmethod
    def _drain(stream: Any, buf: bytearray) -> None:
        while chunk := stream.read1(65536):
            buf.extend(chunk)

    @property
    def pid(self) -> int:
        return self.proc.pid

    def stderr_so_far(self) -> str:
        return bytes(self._err).decode("utf-8", "replace")

    def stdout_so_far(self) -> str:
        return bytes(self._out).decode("utf-8", "replace")

    def wait_for(self, text: str, timeout_s: float = 60.0) -> bool:
        """Wait until ``text`` appears on stderr (True) or the process ends or time runs out (False)."""
        return self._wait_until(lambda err: text in err, timeout_s)

    def wait_for_line(self, line: str | re.Pattern[str], timeout_s: float = 60.0) -> bool:
        """Wait until ``line`` is a whole line of stderr, its newline written too (True), or the process ends or
        time runs out (False). A pattern must match a whole line."""
        if isinstance(line, re.Pattern):
            pattern = line
            return self._wait_until(lambda err: any(pattern.fullmatch(x) for x in err.split("\n")[:-1]), timeout_s)
        return self._wait_until(lambda err: f"\n{line}\n" in f"\n{err}", timeout_s)

    def wait_for_stdout_line(self, start: str, timeout_s: float = 60.0) -> bool:
        """Wait until a whole line of stdout (its newline written too) starts with ``start`` (True), or the process
        ends or time runs out (False)."""
        return self._wait_until(lambda out: any(line.startswith(start) for line in out.split("\n")[:-1]),
                                timeout_s, self.stdout_so_far)

    def _wait_until(self, seen: Callable[[str], bool], timeout_s: float,
                    text: Callable[[], str] | None = None) -> bool:
        so_far = self.stderr_so_far if text is None else text
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if seen(so_far()):
                return True
            if self.proc.poll() is not None:
                for reader in self._readers:  # what the process wrote before it ended
                    reader.join(5.0)
                return seen(so_far())
            time.sleep(0.005)
        return False

    def wait_ready(self, timeout_s: float = 60.0) -> None:
        """Wait until the process is about to call ``main`` (``announce=True``)."""
        assert self.wait_for(READY, timeout_s), f"never got to main: {self.stderr_so_far()!r}"

    def interrupt(self) -> None:
        """Ctrl-C: SIGINT to the process."""
        self.proc.send_signal(signal.SIGINT)

    def finish(self, timeout_s: float = 60.0) -> tuple[int, str, str]:
        """Wait for the end; (exit status, stdout, stderr). A process still running is killed (and fails the test)."""
        try:
            code = self.proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait(5.0)
            raise AssertionError(f"cellcal did not end within {timeout_s} s; "
                                 f"stderr: {self.stderr_so_far()!r}") from None
        for reader in self._readers:
            reader.join(5.0)
        return code, bytes(self._out).decode("utf-8", "replace"), self.stderr_so_far().replace(READY, "", 1)

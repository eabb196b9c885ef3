"""The fault matrix: every step of a calibration run x every fault the emulators and sims inject.

Steps: ``connect``, ``move1..3``, ``capture1..3`` (the paper's three-pose plan) and
``write`` (the result file). Faults, each injected through the real device path at
exactly that step with the public hooks of the sims and emulators:

============ =================================================================== =====================
fault        connect / move k / capture k                                        expected error
============ =================================================================== =====================
drop         connect: the O3R head refuses PCIC (``go_offline``);                DeviceConnectionError
             move: every xArm reply lost from the k-th MOVE_LINE on;             MotionError (the move
                                                                                 is not confirmed, and
                                                                                 never sent again)
             capture: the O3R head drops off the network while sending frame k   DeviceConnectionError
stall        connect: every xArm reply stalls past the reply timeout;            DeviceTimeoutError
             move: the arm stops progressing (blocked) past the move timeout;
             capture: frame k stops half-way, past the capture timeout
corrupt      xArm replies with a bad CRC (connect, from move k on);              ProtocolError
             (move: MotionError, as for drop);
             capture: frame k with a corrupt chunk header
vendor_error xArm controller error 22 (latched at connect; raised in move k);    VendorError
             capture: O3R async error 104000005 with frame k
protective   the sim arm latches error 31 (collision -> protective stop) at       VendorError
_stop        connect / as move k starts / while frame k is captured
interrupt    SIGINT (KeyboardInterrupt) in the camera's connect / as move k      KeyboardInterrupt
             starts / before frame k is rendered
============ =================================================================== =====================

At ``write`` the devices are closed already, so no device fault can reach it; what
can go wrong there is the process being interrupted or the file system failing,
injected at the rename of the finished result: ``interrupt``, ``io_error`` (EIO),
``disk_full`` (ENOSPC) — an :class:`OutputError` that is not a bad path (exit status 1).

Every case checks: the typed error; the time stays within the case's timeout budget
(a bound against hangs, not a speed target); the arm was told to stop, observed on
the simulator/emulator side (``SimArm.stops``, ``XArmEmulator.stop_requests``) —
when the arm itself failed to connect, that no motion ever reached it instead; the
arm is not moving; no thread or descriptor (socket, pty) is left open; the earlier
``result.json`` is byte-identical; nothing but it and the resume journal is in the
directory, and the journal holds exactly the poses measured before the fault.
"""

from __future__ import annotations

import errno
import os
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
from fault_cells import (
    O3R_IO_TIMEOUT_S,
    Probe,
    all_threads,
    cell_document,
    interrupt,
    leftovers,
    make_probe,
    open_fds,
)

from cellcal.core.calibration.calibrator import Calibrator, run_to_file
from cellcal.core.calibration.journal import journal_path, plan_fingerprint, read_journal
from cellcal.devices.errors import (
    DeviceConnectionError,
    DeviceTimeoutError,
    MotionError,
    OutputError,
    ProtocolError,
    VendorError,
)

N_POSES = 3
EVERY = 1000  # "from now on": more faults than the run can send requests in its budget
STEPS = ["connect", *(f"move{k}" for k in range(1, N_POSES + 1)), *(f"capture{k}" for k in range(1, N_POSES + 1))]
DEVICE_FAULTS = ["drop", "stall", "corrupt", "vendor_error", "protective_stop", "interrupt"]
WRITE_FAULTS = ["interrupt", "io_error", "disk_full"]
CASES = [(s, f) for s in STEPS for f in DEVICE_FAULTS] + [("write", f) for f in WRITE_FAULTS]

#: Outcomes, for the summary line printed at the end of the module.
OUTCOMES: dict[str, bool] = {}


@dataclass
class Case:
    camera: str
    arm: str
    expected: type[BaseException]
    arm_connects: bool = True
    #: Seconds the case may take: its timeouts (0.1-2 s) plus slack for a loaded machine, and far
    #: below the injected stalls (30 s) and the default timeouts (60 s), so a hang fails it.
    budget_s: float = 10.0


def _step(step: str) -> tuple[str, int]:
    for kind in ("move", "capture"):
        if step.startswith(kind):
            return kind, int(step[len(kind):])
    return step, 0


def arrange(step: str, fault: str) -> tuple[Case, Callable[[Probe], None]]:
    """The cell and the injection of one matrix case."""
    kind, k = _step(step)

    def when(event: str) -> Callable[[Callable[[], None]], Callable[[str, int], None]]:
        def wrap(action: Callable[[], None]) -> Callable[[str, int], None]:
            def hook(ev: str, n: int) -> None:
                if ev == event and (n >= k if kind != "connect" else True):
                    action()
            return hook
        return wrap

    if kind == "connect":
        if fault == "drop":
            return (Case("o3r-emulated", "sim", DeviceConnectionError, budget_s=2.0 + O3R_IO_TIMEOUT_S + 10.0),
                    lambda p: setattr(p.calibrator.camera, "on_emulator_started", lambda emu: emu.go_offline()))
        if fault in ("stall", "corrupt"):
            spoil = "stall" if fault == "stall" else "corrupt_crc"

            def setup(p: Probe) -> None:
                def started(emu: Any) -> None:
                    p.xarm.append(emu)
                    emu.inject(spoil, count=EVERY, stall_s=30.0)
                p.calibrator.arm.inner.on_emulator_started = started
            return (Case("sim", "xarm-emulated", DeviceTimeoutError if fault == "stall" else ProtocolError,
                         arm_connects=False), setup)
        if fault == "vendor_error":
            return Case("sim", "xarm-emulated", VendorError), lambda p: p.sim_arm.set_error(22)
        if fault == "protective_stop":
            return (Case("sim", "sim", VendorError),
                    lambda p: setattr(p.sim_arm, "fault_hook", when("connect")(lambda: p.sim_arm.set_error(31))))
        return (Case("sim", "sim", KeyboardInterrupt),
                lambda p: setattr(p.sim_camera, "fault_hook", when("connect")(interrupt)))

    if kind == "move":
        if fault in ("drop", "corrupt"):
            spoil = "drop" if fault == "drop" else "corrupt_crc"
            return (Case("sim", "xarm-emulated", MotionError),
                    lambda p: setattr(p.sim_arm, "fault_hook",
                                      when("move")(lambda: p.xarm[-1].inject(spoil, count=EVERY))))
        if fault == "stall":
            return (Case("sim", "xarm-emulated", DeviceTimeoutError),
                    lambda p: setattr(p.sim_arm, "fault_hook", when("move")(p.sim_arm.freeze_motion)))
        if fault == "vendor_error":
            return (Case("sim", "xarm-emulated", VendorError),
                    lambda p: setattr(p.sim_arm, "fault_hook", when("move")(lambda: p.sim_arm.set_error(22))))
        if fault == "protective_stop":
            return (Case("sim", "sim", VendorError),
                    lambda p: setattr(p.sim_arm, "fault_hook", when("move")(lambda: p.sim_arm.set_error(31))))
        return (Case("sim", "sim", KeyboardInterrupt),
                lambda p: setattr(p.sim_arm, "fault_hook", when("move")(interrupt)))

    assert kind == "capture"
    if fault in ("drop", "stall", "corrupt", "vendor_error"):
        def inject(p: Probe) -> None:
            emu = p.o3r[-1]
            if fault == "drop":
                emu.go_offline()
            elif fault == "stall":
                emu.inject_fault("stall", seconds=30.0)
            elif fault == "corrupt":
                emu.inject_fault("corrupt", field="chunk_size")
            else:
                emu.inject_fault("async_error", code=104000005, message="emulated overtemperature")
        expected = {"drop": DeviceConnectionError, "stall": DeviceTimeoutError, "corrupt": ProtocolError,
                    "vendor_error": VendorError}[fault]
        return (Case("o3r-emulated", "sim", expected),
                lambda p: setattr(p.sim_camera, "fault_hook", when("capture")(lambda: inject(p))))
    if fault == "protective_stop":
        return (Case("sim", "sim", VendorError),
                lambda p: setattr(p.sim_camera, "fault_hook", when("capture")(lambda: p.sim_arm.set_error(31))))
    return Case("sim", "sim", KeyboardInterrupt), lambda p: setattr(p.sim_camera, "fault_hook",
                                                                    when("capture")(interrupt))


def poses_before(step: str) -> int:
    """Poses completely measured before the fault of ``step`` (what the journal must hold)."""
    kind, k = _step(step)
    return {"connect": 0, "write": N_POSES}.get(kind, k - 1)


@pytest.fixture(scope="module")
def earlier_result(tmp_path_factory: pytest.TempPathFactory) -> bytes:
    """A complete result.json from an earlier, successful run."""
    out = tmp_path_factory.mktemp("earlier") / "result.json"
    run_to_file(make_probe(cell_document()).calibrator, out)
    return out.read_bytes()


@pytest.fixture(scope="module", autouse=True)
def matrix_summary(request: pytest.FixtureRequest) -> Iterator[None]:
    yield
    reporter = request.config.pluginmanager.get_plugin("terminalreporter")
    lost = sum(1 for ok in OUTCOMES.values() if not ok)
    line = (f"fault matrix: {len(CASES)} fault cases ({len(STEPS)} device steps x {len(DEVICE_FAULTS)} faults "
            f"+ write x {len(WRITE_FAULTS)}), {len(OUTCOMES)} run, {lost} lost results")
    capman = request.config.pluginmanager.getplugin("capturemanager")
    if reporter is None or capman is None:  # pragma: no cover - plugins disabled
        print(line)
        return
    with capman.global_and_fixture_disabled():  # past the output capture, into the session's output
        reporter.write_line("")
        reporter.write_line(line)


def test_matrix_covers_every_step_and_fault() -> None:
    """The cases are written out here, independently of the constants that build them."""
    device_steps = ["connect", "move1", "move2", "move3", "capture1", "capture2", "capture3"]
    faults = ["drop", "stall", "corrupt", "vendor_error", "protective_stop", "interrupt"]
    expected = {(s, f) for s in device_steps for f in faults} | {("write", "interrupt"), ("write", "io_error"),
                                                                   ("write", "disk_full")}
    assert len(expected) == 45 and len(CASES) == len(set(CASES)) and set(CASES) == expected
    errors = {"drop": (DeviceConnectionError, MotionError), "stall": (DeviceTimeoutError,),
              "corrupt": (ProtocolError, MotionError), "vendor_error": (VendorError,),
              "protective_stop": (VendorError,), "interrupt": (KeyboardInterrupt,)}
    for step, fault in CASES:
        if step != "write":
            case, inject = arrange(step, fault)  # every device case has an injection and a typed error
            assert callable(inject) and case.expected in errors[fault], (step, fault, case.expected)
            assert case.budget_s <= 20.0


@pytest.mark.parametrize(("step", "fault"), CASES)
def test_fault(step: str, fault: str, tmp_path: Path, earlier_result: bytes,
               monkeypatch: pytest.MonkeyPatch) -> None:
    out_dir = tmp_path / "out"
    out_dir.mkdir()
    result = out_dir / "result.json"
    result.write_bytes(earlier_result)
    if step == "write":
        case = Case("sim", "sim", KeyboardInterrupt if fault == "interrupt" else OutputError)
        probe = make_probe(cell_document())
        real_replace = os.replace

        def failing_replace(src: Any, dst: Any, *args: Any, **kwargs: Any) -> None:
            if Path(dst) == result:
                if fault == "interrupt":
                    raise KeyboardInterrupt
                raise OSError(errno.EIO if fault == "io_error" else errno.ENOSPC,
                              os.strerror(errno.EIO if fault == "io_error" else errno.ENOSPC))
            real_replace(src, dst, *args, **kwargs)

        monkeypatch.setattr(os, "replace", failing_replace)
    else:
        case, inject = arrange(step, fault)
        probe = make_probe(cell_document(case.camera, case.arm))
        inject(probe)

    threads, fds = all_threads(), open_fds()
    started = time.monotonic()
    with pytest.raises(case.expected) as info:
        run_to_file(probe.calibrator, result)
    elapsed = time.monotonic() - started
    monkeypatch.undo()

    OUTCOMES[f"{step}-{fault}"] = result.read_bytes() == earlier_result
    assert result.read_bytes() == earlier_result, "the earlier result.json changed"
    if case.expected is not KeyboardInterrupt:
        assert "\n" not in str(info.value) and str(info.value)
    assert not isinstance(info.value, OutputError) or not info.value.bad_path  # a failing disk: exit status 1
    assert elapsed <= case.budget_s, f"took {elapsed:.2f} s, budget {case.budget_s} s"

    # the arm was told to stop (seen by the simulator or the emulator), and is still
    sim_arm = probe.sim_arm
    if step == "write":
        assert sim_arm.moves_started == N_POSES  # the plan had finished; the devices were closed normally
    elif not case.arm_connects:
        assert sim_arm.moves_started == 0, "a motion reached an arm that never connected"
    elif case.arm == "xarm-emulated":
        assert probe.xarm and probe.xarm[-1].stop_requests >= 1, "the xArm controller never got a stop"
    else:
        assert sim_arm.stops >= 1, "the sim arm never got a stop"
    assert not sim_arm.is_moving()
    assert not probe.calibrator.camera.connected and not probe.calibrator.arm.connected

    leaked_threads, leaked_fds = leftovers(threads, fds)
    assert not leaked_threads, f"leaked threads: {leaked_threads}"
    assert not leaked_fds, f"leaked descriptors: {sorted(leaked_fds)}"

    names = sorted(p.name for p in out_dir.iterdir())
    journal = journal_path(result)
    saved = poses_before(step)
    assert names == (["result.json", journal.name] if saved else ["result.json"])
    if saved:
        cal: Calibrator = probe.calibrator
        entries = read_journal(journal, plan_fingerprint(cal.config.document, cal.poses))
        assert [e.index for e in entries] == list(range(saved))
        for e in entries:  # each record is the measured pose of its plan index, with its measurements
            assert e.pose["index"] == e.index and e.pose["measurements"]
            commanded = e.pose["commanded_flange_pose"]["translation_m"]
            assert commanded == pytest.approx(list(cal.poses[e.index].translation), abs=1e-12)

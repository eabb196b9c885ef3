"""The UR emulator in a child process, driven over its stdin/stdout: :class:`UREmulatorProcess`.

ur_rtde 1.6's Python constructors hold the GIL while they negotiate with the controller,
so an emulator thread in the same interpreter could never answer them: a process that
uses ur_rtde runs the emulator as a child (docs/adr/0017-ur-emulator.md). The child is
``python -m cellcal.sims.ur --control``; each stdin line is a JSON command
``{"op": ..., "args": {...}}`` and each stdout line after ``ready`` is its JSON reply.
"""

from __future__ import annotations

import contextlib
import json
import os
import selectors
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from typing import IO, Any

from cellcal.devices.errors import DeviceConnectionError, DeviceTimeoutError, ProtocolError
from cellcal.devices.geometry.vendor_poses import pose_from_ur

from .emulator import UREmulator

#: Longest reply line read from the child, bytes.
MAX_LINE_BYTES = 1 << 20


def _set_flange_pose(emulator: UREmulator, pose: Sequence[float]) -> None:
    arm: Any = emulator.state.arm
    if arm.is_moving():
        raise ValueError("the arm is moving")
    arm.world.arm.set_flange_pose(pose_from_ur(pose))


def commands(emulator: UREmulator) -> dict[str, Callable[..., Any]]:
    """The operations a controlling process may call, by name."""
    return {
        "snapshot": emulator.snapshot,
        "safety_stop": emulator.safety_stop,
        "release_emergency_stop": emulator.release_emergency_stop,
        "refuse_script": emulator.refuse_script,
        "freeze_stream": emulator.freeze_stream,
        "unfreeze_stream": emulator.unfreeze_stream,
        "send_raw_rtde": emulator.send_raw_rtde,
        "drop_connections": emulator.drop_connections,
        "accept_connections": emulator.accept_connections,
        "set_remote_control": emulator.set_remote_control,
        "reset": emulator.reset,
        "set_time_scale": emulator.set_time_scale,
        "set_unlock_delay": emulator.set_unlock_delay,
        "set_flange_pose": lambda pose: _set_flange_pose(emulator, pose),
        "dashboard": emulator.dashboard.reply,
    }


def serve_commands(emulator: UREmulator, stdin: IO[str], stdout: IO[str]) -> None:
    """Answer JSON commands from ``stdin`` until it closes or ``{"op": "quit"}`` arrives."""
    table = commands(emulator)
    for line in stdin:
        if not line.strip():
            continue
        try:
            request = json.loads(line)
            if request.get("op") == "quit":
                return
            result = table[request["op"]](**request.get("args", {}))
            reply = {"ok": True, "result": result}
        except Exception as exc:  # reported to the parent, which raises it there
            reply = {"ok": False, "error": f"{type(exc).__name__}: {exc}"}
        stdout.write(json.dumps(reply) + "\n")
        stdout.flush()


class UREmulatorProcess:
    """Run ``python -m cellcal.sims.ur`` as a child and call its operations.

    Args:
        host: Loopback address, or ``"auto"`` for a free 127.0.0.N chosen by the child.
        arm_config: Keys of the simulated arm's config (``SimArmConfig``).
        flange_pose: Start flange pose, UR vector ``[x, y, z, rx, ry, rz]`` (m, rad).
        powered: Start powered with brakes released.
        unlock_delay_s: Minimum time from a protective stop to its unlock, s.
        seed: Seed of the arm's read-back noise.
        verbose: The child logs program starts/stops and faults to stderr.

    Attributes:
        host: The address the child listens on (once started).
    """

    def __init__(self, host: str = "auto", *, arm_config: dict[str, Any] | None = None,
                 flange_pose: Sequence[float] | None = None, powered: bool = True,
                 unlock_delay_s: float = 5.0, seed: int = 0, verbose: bool = False) -> None:
        self.host = host
        self._argv = [sys.executable, "-m", "cellcal.sims.ur", "--host", host, "--control",
                      "--unlock-delay", repr(float(unlock_delay_s)), "--seed", str(int(seed)),
                      "--arm-config", json.dumps(arm_config or {})]
        if flange_pose is not None:
            self._argv += ["--flange-pose", *(repr(float(v)) for v in flange_pose)]
        if not powered:
            self._argv.append("--powered-off")
        if verbose:
            self._argv.append("--verbose")
        self._proc: subprocess.Popen[bytes] | None = None
        self._buf = b""

    def start(self, timeout: float = 30.0) -> str:
        """Start the child and wait for its ``ready`` line; returns the address it listens on.

        Raises:
            DeviceConnectionError: If the child exits or reports an error instead.
            DeviceTimeoutError: If it is not ready within ``timeout``.
        """
        self._proc = subprocess.Popen(self._argv, stdin=subprocess.PIPE, stdout=subprocess.PIPE)
        try:
            line = self._read_line(time.monotonic() + timeout)
        except Exception:
            self.close()
            raise
        words = line.split()
        if not words or words[0] != "ready" or len(words) < 2:
            self.close()
            raise DeviceConnectionError(f"ur emulator: unexpected first line {line!r}")
        self.host = words[1]
        return self.host

    def __enter__(self) -> UREmulatorProcess:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def running(self) -> bool:
        """Whether the child is alive."""
        return self._proc is not None and self._proc.poll() is None

    def call(self, op: str, timeout: float = 5.0, **args: Any) -> Any:
        """Call one emulator operation in the child and return its result.

        Raises:
            ProtocolError: If the child reports an error (its message included).
            DeviceTimeoutError: If no reply comes within ``timeout``.
        """
        proc = self._proc
        if proc is None or proc.stdin is None or proc.poll() is not None:
            raise DeviceConnectionError("ur emulator: the child process is not running")
        proc.stdin.write((json.dumps({"op": op, "args": args}) + "\n").encode())
        proc.stdin.flush()
        reply = json.loads(self._read_line(time.monotonic() + timeout))
        if not reply.get("ok"):
            raise ProtocolError(f"ur emulator: {op} failed: {reply.get('error')}")
        return reply.get("result")

    def snapshot(self, timeout: float = 5.0) -> dict[str, Any]:
        """The emulator's state (see :meth:`UREmulator.snapshot`)."""
        result: dict[str, Any] = self.call("snapshot", timeout)
        return result

    def close(self, timeout: float = 5.0) -> None:
        """Ask the child to quit, wait for it (killing it after ``timeout``) and close the pipes."""
        proc, self._proc = self._proc, None
        if proc is None:
            return
        if proc.stdin is not None:
            with contextlib.suppress(OSError, ValueError):
                proc.stdin.write(b'{"op": "quit"}\n')
                proc.stdin.close()
        try:
            proc.wait(timeout)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout)
        if proc.stdout is not None:
            proc.stdout.close()

    def _read_line(self, deadline: float) -> str:
        proc = self._proc
        assert proc is not None and proc.stdout is not None
        fd = proc.stdout.fileno()
        with selectors.DefaultSelector() as sel:
            sel.register(fd, selectors.EVENT_READ)
            while b"\n" not in self._buf:
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    raise DeviceTimeoutError("ur emulator: no reply from the child process in time")
                if sel.select(min(remaining, 0.5)):
                    chunk = os.read(fd, 65536)
                    if not chunk:
                        raise DeviceConnectionError(f"ur emulator: child exited (status {proc.poll()})")
                    self._buf += chunk
                    if len(self._buf) > MAX_LINE_BYTES:
                        raise ProtocolError("ur emulator: reply line too long")
        line, self._buf = self._buf.split(b"\n", 1)
        return line.decode("utf-8", errors="replace").strip()

"""How the emulated O3R VPU behaves (:class:`EmulatorOptions`) and the device facts its defaults copy."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from .wire import DISTANCE_RESOLUTION_M

#: Optical frame in the head frame of a real O3R222 (transX/Y/Z m, rotX/Y/Z rad; the TOF_INFO v4 capture).
FACTORY_OPTIC_TO_HEAD = (0.0, 0.0, 0.00841006, -0.0204563, 0.0181109, -0.00622652)
#: Uptime the boot clock starts from, s (the real capture's clock read 3.76 days).
BOOT_UPTIME_S = 324896.0
#: VPU ports a camera head can be plugged into (``port6`` is the IMU).
HEAD_PORTS = ("port0", "port1", "port2", "port3", "port4", "port5")


@dataclass(frozen=True)
class EmulatorOptions:
    """How the emulated VPU behaves (defaults: like the device). Every 3D head starts with the same values.

    Attributes:
        port_name: VPU port of the (first) 3D head, ``portN``.
        state: Initial port state (RUN, IDLE, CONF).
        frame_rate_hz: Frame rate in RUN.
        max_frame_rate_hz: Largest frame rate the tree accepts (30 as on a VPU; raise for load tests).
        distance_resolution_m: Metres per distance count (10 / 65535 as on a VPU).
        optic_to_head: Factory optical-to-head extrinsic (transX/Y/Z m, rotX/Y/Z rad).
        header_version: Chunk header version for every chunk, or None for the real mix.
        tof_info_version: TOF_INFO version 1..4.
        confidence_bits: 16 (current firmware) or 8 (older firmware).
        mode: Initial mode of the 3D head (``cyclic_4m_2m_4m_2m`` cycles measurement blocks).
        state_change_s: How long a state change takes (the ``set`` answers after it), s.
        clock: ``"boot"`` (time since boot, as a VPU without SNTP) or ``"unix"`` (the source's time).
        frames: ``"per_frame"`` (one source capture per frame, deterministic) or ``"per_pose"``
            (one capture per camera pose plus fresh noise per frame, for load rates).
        noise_scale: Noise multiplier of ``per_pose`` frames.
        capture_timeout_s: Timeout passed to ``source.capture``.
    """

    port_name: str = "port2"
    state: str = "RUN"
    frame_rate_hz: float = 20.0
    max_frame_rate_hz: float = 30.0
    distance_resolution_m: float = DISTANCE_RESOLUTION_M
    optic_to_head: tuple[float, float, float, float, float, float] = FACTORY_OPTIC_TO_HEAD
    header_version: int | None = None
    tof_info_version: int = 4
    confidence_bits: int = 16
    mode: str = "standard_range4m"
    state_change_s: float = 0.3
    clock: Literal["boot", "unix"] = "boot"
    frames: Literal["per_frame", "per_pose"] = "per_frame"
    noise_scale: float = 1.0
    capture_timeout_s: float = 5.0


def two_d_partners(heads: list[str]) -> list[str]:
    """The 2D ports of the 3D heads on ``heads``, as cables are plugged on a VPU.

    A head's 2D imager sits two ports below its 3D one (3D port2 -> 2D port0, port3 -> port1),
    a 3D head on port0 / port1 has its 2D on port1 / port0; a port that already carries a 3D
    head, or a 2D port already given, is left out (so four 3D heads on port2..port5 have two 2D).
    """
    out: list[str] = []
    for name in heads:
        n = int(name.removeprefix("port"))
        partner = f"port{n - 2}" if n >= 2 else f"port{1 - n}"
        if partner not in heads and partner not in out:
            out.append(partner)
    return out

"""The ``[arm]`` section of the ``ur`` backend, and UR's own motion limits."""

from __future__ import annotations

from dataclasses import dataclass, field

#: UR's own limits on Cartesian tool motion (URScript ``movel``).
UR_MAX_TOOL_SPEED_M_S = 3.0
UR_MAX_TOOL_ACCELERATION_M_S2 = 150.0


@dataclass(frozen=True)
class URConfig:
    """``[arm]`` section for ``backend = "ur"``.

    Attributes:
        host: Controller IP address or host name.
        timeout_s: Default I/O timeout, s (connect uses it too: script upload takes ~1 s).
        stale_after_s: A receive timestamp unchanged this long marks a stale stream, s.
        max_speed_m_s: Highest tool speed this backend accepts (<= UR's 3 m/s).
        max_acceleration_m_s2: Highest tool acceleration accepted (<= UR's 150 m/s²).
        stop_deceleration_m_s2: Deceleration used by :meth:`URArm.stop`, m/s².
        arrival_tolerance_m: A finished move must end this close to the target, m.
        arrival_tolerance_rad: ... and this close in orientation, rad.
        poll_interval_s: Status polling period while a move runs, s.
        set_tcp_to_flange: Zero the TCP offset at connect (cellcal poses are flange poses).
        use_dashboard: Use the dashboard server (port 29999) for identity and recovery.
        dashboard_port: Dashboard server port.
        allow_power_on: Let :meth:`URArm.clear_errors` power the arm on and release brakes.
        isolate: Run ur_rtde in a worker process, so a crash in it is an error and not the end of
            cellcal (ADR 0038); ``false`` runs it in-process, for a debugger only.
    """

    host: str
    timeout_s: float = field(default=5.0, metadata={"gt": 0, "doc": "default I/O timeout, s"})
    stale_after_s: float = field(default=0.1, metadata={"gt": 0, "le": 10})
    max_speed_m_s: float = field(default=UR_MAX_TOOL_SPEED_M_S,
                                 metadata={"gt": 0, "le": UR_MAX_TOOL_SPEED_M_S})
    max_acceleration_m_s2: float = field(default=UR_MAX_TOOL_ACCELERATION_M_S2,
                                         metadata={"gt": 0, "le": UR_MAX_TOOL_ACCELERATION_M_S2})
    stop_deceleration_m_s2: float = field(default=10.0, metadata={"gt": 0, "le": UR_MAX_TOOL_ACCELERATION_M_S2})
    arrival_tolerance_m: float = field(default=1e-3, metadata={"gt": 0})
    arrival_tolerance_rad: float = field(default=5e-3, metadata={"gt": 0})
    poll_interval_s: float = field(default=0.01, metadata={"gt": 0, "le": 1})
    set_tcp_to_flange: bool = True
    use_dashboard: bool = True
    dashboard_port: int = field(default=29999, metadata={"gt": 0, "lt": 65536})
    allow_power_on: bool = False
    isolate: bool = True

    def __post_init__(self) -> None:
        if not self.host.strip():
            raise ValueError("host must not be empty")

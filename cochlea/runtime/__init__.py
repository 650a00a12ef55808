"""The runtime layer: a scenario's controllers at the control rate against a backend (the
simulated robot, or the Dynamixel bridge above this layer), under the safety supervisor, with
the log written behind the loop."""

from .backend import Backend, BackendError
from .loop import (
           FIFO_PRIORITY,
           POLICIES,
           RealTimeLoop,
           RealtimeOptions,
           apply_realtime,
           check_realtime_options,
           raw_columns,
           write_raw_columns,
)
from .sim_backend import SimBackend
from .supervisor import (
           EXIT_BACKEND,
           EXIT_OK,
           OVERRUN_POLICY,
           STOP_CODES,
           Limits,
           OverrunWatch,
           Stop,
           Supervisor,
           build_supervisor,
           first_violation,
           verdict,
)

__all__ = ["Backend", "BackendError", "RealTimeLoop", "raw_columns", "write_raw_columns",
           "FIFO_PRIORITY", "POLICIES", "RealtimeOptions", "apply_realtime",
           "check_realtime_options", "OverrunWatch", "OVERRUN_POLICY",
           "SimBackend", "EXIT_BACKEND", "EXIT_OK", "STOP_CODES", "Limits", "Stop", "Supervisor",
           "build_supervisor", "first_violation", "verdict"]

"""The tunables of one service instance (:class:`ServiceOptions`), apart from the server so
that its parts (dispatch, state publishing) and the command line read them without importing
the server."""
from __future__ import annotations

from dataclasses import dataclass

from falcon_plan.errors import InvalidParameterError
from service.codec import MAX_PAYLOAD_BYTES
from service.handlers import MAX_TIME_BUDGET_S


@dataclass(frozen=True)
class ServiceOptions:
    """Tunables of one instance (all have safe defaults).

    Attributes
    ----------
    state_rate_hz : device state publication rate [Hz].
    planning_workers : planner processes (or threads), each planning one request at a time.
    planning_processes : True (default): workers are processes, which plan in parallel (the
        solver holds the interpreter lock); False: threads in this process (for a planner
        that cannot be imported by name; a late or cancelled plan is answered on time but its
        thread stays busy until the planner returns).
    request_cap_s : longest any plan request or goal planning phase may take from its
        arrival, queue time included [s]; a request's ``timeout_s`` can only shorten it.
    max_pending_plans : plan requests allowed to wait for a worker before ``overloaded``.
    plan_cache_size : plans remembered by (problem, options); 0 disables the cache.
    queue_limit : pending goals allowed; goal_history : finished goals kept for queries.
    progress_rate_hz : most goal progress publications per second.
    max_payload_bytes : largest request accepted [bytes].
    record_dir : folder where every goal is recorded as an MCAP file ``<goal id>.mcap`` (None:
        no recordings).
    foxglove_port : port of the Foxglove live view on 127.0.0.1 (None: no live view; 0: any
        free port).
    """

    state_rate_hz: float = 50.0
    planning_workers: int = 1
    planning_processes: bool = True
    request_cap_s: float = MAX_TIME_BUDGET_S
    max_pending_plans: int = 64
    plan_cache_size: int = 64
    queue_limit: int = 16
    goal_history: int = 256
    progress_rate_hz: float = 50.0
    max_payload_bytes: int = MAX_PAYLOAD_BYTES
    record_dir: str | None = None
    foxglove_port: int | None = None

    def __post_init__(self) -> None:
        if not 0 < self.state_rate_hz <= 1000:
            raise InvalidParameterError(f"state_rate_hz must be in (0, 1000], got {self.state_rate_hz}")
        if not 1 <= self.planning_workers <= 64:
            raise InvalidParameterError(f"planning_workers must be in [1, 64], got {self.planning_workers}")
        if not 0 < self.request_cap_s <= 3600:
            raise InvalidParameterError(f"request_cap_s must be in (0, 3600] s, got {self.request_cap_s}")
        for name in ("max_pending_plans", "queue_limit", "goal_history", "max_payload_bytes"):
            if getattr(self, name) < 1:
                raise InvalidParameterError(f"{name} must be at least 1, got {getattr(self, name)}")


__all__ = ["ServiceOptions"]

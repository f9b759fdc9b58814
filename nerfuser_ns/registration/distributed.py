"""Where the graph mode's independent work runs: per NeRF (render, lift keypoints) and per candidate pair (register
it), in this process one after the other, or as Ray tasks on this machine or a cluster.

Both run the same module-level functions on the same arguments and return the results in order, so a registration
comes out the same either way. The render cache on disk stays the source of truth: a task writes its NeRF's render
folder (atomically, as in a serial run) and later runs reuse it; on a cluster every worker must see the work folder.
Ray is optional (the ``city`` extra) and imported only when asked for (its import takes seconds).
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from typing import Any, Protocol

from nerfuser_ns.registration.config import RegistrationError

RAY_MISSING = 'distributing the work with Ray needs Ray: pip install "nerfuser_ns[city]"'


class Executor(Protocol):
    """Runs ``fn(*args)`` for every args tuple; results in the order given."""

    name: str

    def map(self, fn: Callable[..., Any], args: Sequence[tuple]) -> list[Any]: ...

    def close(self) -> None: ...


class SerialExecutor:
    """In this process, one call after the other."""

    name = "serial"

    def map(self, fn: Callable[..., Any], args: Sequence[tuple]) -> list[Any]:
        return [fn(*a) for a in args]

    def close(self) -> None:
        pass


class RayExecutor:
    """One Ray task per call (one CPU each). Connects to ``address`` (e.g. ``auto`` or ``ray://head:10001``), or starts
    Ray on this machine when it is None; :meth:`close` stops only a Ray this executor started."""

    name = "ray"

    def __init__(self, address: str | None = None):
        try:
            import ray  # lazy: only this executor needs it, and its import takes seconds
        except ImportError:
            raise RegistrationError(RAY_MISSING) from None
        # Ray would otherwise report usage statistics over the network
        os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
        self._ray = ray
        self._started = not ray.is_initialized()
        if self._started:
            try:
                ray.init(address=address, include_dashboard=False, log_to_driver=False)
            except (ConnectionError, ValueError, RuntimeError) as e:
                where = "on this machine" if address is None else f"at {address}"
                raise RegistrationError(f"cannot start or reach Ray {where}: {str(e).splitlines()[0]}") from None

    def map(self, fn: Callable[..., Any], args: Sequence[tuple]) -> list[Any]:
        remote = self._ray.remote(num_cpus=1)(fn)
        stored: dict[int, Any] = {}

        def ref(x: Any) -> Any:
            # an argument shared by several calls (every NeRF's features, the renderers) is stored once
            if isinstance(x, (list, tuple, dict)) or hasattr(x, "__dict__"):
                if id(x) not in stored:
                    stored[id(x)] = self._ray.put(x)
                return stored[id(x)]
            return x

        return self._ray.get([remote.remote(*[ref(x) for x in a]) for a in args])

    def close(self) -> None:
        if self._started and self._ray.is_initialized():
            self._ray.shutdown()


def make_executor(kind: str, address: str | None = None) -> Executor:
    """The executor ``kind`` names (serial or ray); bad input is one :class:`RegistrationError` line."""
    if kind == "serial":
        return SerialExecutor()
    if kind == "ray":
        return RayExecutor(address)
    raise RegistrationError(f"unknown --graph.executor {kind!r}; use serial or ray")

"""Where the graph mode's independent work runs: per NeRF (render, lift keypoints) and per candidate pair (register
it), in this process one after the other, or as Ray tasks on this machine or a cluster.

Both run the same module-level functions on the same arguments and return the results in order, so a registration
comes out the same either way. The render cache on disk stays the source of truth: a task writes its NeRF's render
folder (atomically, as in a serial run) and later runs reuse it; on a cluster every worker must see the work folder.
Ray is optional (the ``city`` extra) and imported only when asked for (its import takes seconds).
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Sequence
from typing import Any, Protocol

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

from nerfuser_ns.registration.config import RegistrationError

RAY_MISSING = 'distributing the work with Ray needs Ray: pip install "nerfuser_ns[city]"'
RAY_CPUS_PER_TASK = 1
"""CPUs each Ray task asks for (and the threads its pycolmap calls use, unless a count is set)."""


def timed(fn: Callable[..., Any], *args: Any) -> tuple[Any, float]:
    """``fn(*args)`` and the seconds it took where it ran (a task's own time, without queueing or transfers)."""
    t0 = time.perf_counter()
    out = fn(*args)
    return out, time.perf_counter() - t0


class Executor(Protocol):
    """Runs ``fn(*args)`` for every args tuple; results in the order given. Each task's own seconds are kept per
    ``description`` in :attr:`task_seconds`."""

    name: str
    task_seconds: dict[str, list[float]]

    def map(self, fn: Callable[..., Any], args: Sequence[tuple], description: str = "task",
            uses_gpu: bool = False) -> list[Any]: ...  # fmt: skip

    def task_threads(self, requested: int) -> int:
        """The threads a task's pycolmap calls may use, given the count asked for (-1: all cores)."""
        ...

    def close(self) -> None: ...


class SerialExecutor:
    """In this process, one call after the other."""

    name = "serial"

    def __init__(self) -> None:
        self.task_seconds: dict[str, list[float]] = {}

    def map(self, fn: Callable[..., Any], args: Sequence[tuple], description: str = "task",
            uses_gpu: bool = False) -> list[Any]:  # fmt: skip
        """``uses_gpu`` is for the Ray executor: here the tasks run on this process's device."""
        out = [timed(fn, *a) for a in args]
        self.task_seconds.setdefault(description, []).extend(round(t, 3) for _, t in out)
        return [r for r, _ in out]

    @staticmethod
    def task_threads(requested: int) -> int:
        """As asked: one task at a time has the cores to itself."""
        return requested

    def close(self) -> None:
        pass


class RayExecutor:
    """One Ray task per call, one CPU each (:data:`RAY_CPUS_PER_TASK`), and ``gpus_per_task`` GPUs for tasks that render
    (``uses_gpu``): by default one GPU when the cluster has any (Ray hides the GPUs from a task that asks for none, so a
    NeRF loaded on ``cuda`` needs it), none otherwise. Connects to ``address`` (e.g. ``auto`` or ``ray://head:10001``),
    or starts Ray on this machine when it is None; :meth:`close` stops only a Ray this executor started. Progress over
    the tasks of each :meth:`map` on ``console``."""

    name = "ray"

    def __init__(self, address: str | None = None, gpus_per_task: float | None = None,
                 console: Console | None = None):  # fmt: skip
        try:
            import ray  # lazy: only this executor needs it, and its import takes seconds
        except ImportError:
            raise RegistrationError(RAY_MISSING) from None
        # Ray would otherwise report usage statistics over the network
        os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
        self._ray = ray
        self._console = console or Console(quiet=True)
        self.task_seconds: dict[str, list[float]] = {}
        self._started = not ray.is_initialized()
        if self._started:
            try:
                ray.init(address=address, include_dashboard=False, log_to_driver=False)
            except Exception as e:  # noqa: BLE001 - Ray raises bare Exceptions too (e.g. a node that timed out starting)
                where = "on this machine" if address is None else f"at {address}"
                raise RegistrationError(f"cannot start or reach Ray {where}: {str(e).splitlines()[0]}") from None
        if gpus_per_task is None:
            gpus_per_task = 1.0 if ray.cluster_resources().get("GPU", 0) > 0 else 0.0
        self.gpus_per_task = float(gpus_per_task)

    def map(self, fn: Callable[..., Any], args: Sequence[tuple], description: str = "task",
            uses_gpu: bool = False) -> list[Any]:  # fmt: skip
        remote = self._ray.remote(num_cpus=RAY_CPUS_PER_TASK, num_gpus=self.gpus_per_task if uses_gpu else 0)(timed)
        stored: dict[int, Any] = {}

        def ref(x: Any) -> Any:
            # an argument shared by several calls (every NeRF's features, the renderers) is stored once
            if isinstance(x, (list, tuple, dict)) or hasattr(x, "__dict__"):
                if id(x) not in stored:
                    stored[id(x)] = self._ray.put(x)
                return stored[id(x)]
            return x

        pending = [remote.remote(fn, *[ref(x) for x in a]) for a in args]
        index = {r: n for n, r in enumerate(pending)}
        results: list[Any] = [None] * len(pending)
        columns = (TextColumn(f"Ray: {description} tasks"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn())
        with Progress(*columns, console=self._console, transient=True) as progress:
            bar = progress.add_task(description, total=len(pending))
            while pending:
                done, pending = self._ray.wait(pending, num_returns=1)
                for r in done:
                    results[index[r]] = self._ray.get(r)
                    progress.advance(bar)
        self.task_seconds.setdefault(description, []).extend(round(t, 3) for _, t in results)
        return [r for r, _ in results]

    @staticmethod
    def task_threads(requested: int) -> int:
        """A task's CPUs when all cores are asked for: Ray runs as many tasks at once as a node has CPUs, so tasks
        that each took every core would oversubscribe it."""
        return requested if requested > 0 else RAY_CPUS_PER_TASK

    def close(self) -> None:
        if self._started and self._ray.is_initialized():
            self._ray.shutdown()


def make_executor(kind: str, address: str | None = None, gpus_per_task: float | None = None,
                  console: Console | None = None) -> Executor:  # fmt: skip
    """The executor ``kind`` names (serial or ray); bad input is one :class:`RegistrationError` line."""
    if kind == "serial":
        return SerialExecutor()
    if kind == "ray":
        return RayExecutor(address, gpus_per_task, console)
    raise RegistrationError(f"unknown --graph.executor {kind!r}; use serial or ray")

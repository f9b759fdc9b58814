"""``ns-nerfuser-view``: nerfstudio's live viewer on a fused scene, straight from a fusion spec or a fused run.

Example::

    ns-nerfuser-view fusion.json                 # a fusion spec (or its folder, or a registration file)
    ns-nerfuser-view outputs/x/nerfuser/run      # a fused run (what ns-viewer --load-config opens too)

Opens the same viewer as ``ns-viewer --load-config <fused run>/config.yml`` (see :mod:`nerfuser_ns.viewer`) without
``ns-train nerfuser`` first. Serves on the loopback interface by default; pass ``--host 0.0.0.0`` to let other
machines connect. Bad input prints one red line and exits with status 1.
"""

from __future__ import annotations

import os
import signal
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import tyro
from rich.console import Console

from nerfuser_ns.blending import BlendMethod
from nerfuser_ns.runs import check_device, default_device

ERR_CONSOLE = Console(stderr=True, soft_wrap=True)


@dataclass
class ViewCommand:
    """Open nerfstudio's live viewer on fused NeRFs: a fusion spec (no ns-train needed) or a fused run."""

    path: tyro.conf.Positional[Path]
    """A fusion spec (fusion.json, a folder holding it, or a registration file), or a fused run's config.yml (or
    its folder)."""
    host: str = "127.0.0.1"
    """Interface to serve on (0.0.0.0: every interface, for other machines)."""
    port: int | None = None
    """Port to serve on (default: 7007, or the next free one)."""
    device: str = field(default_factory=default_device)
    """Torch device the NeRFs render on (default: cuda when torch sees a GPU, else cpu)."""
    max_res: int | None = None
    """The panel's initial "Max res" (default: 256 on the CPU, nerfstudio's 512 otherwise)."""
    blend_method: BlendMethod | None = None
    """Initial blend method (default: the run's, or idw-sample); the panel changes it live."""
    gamma: float | None = None
    """Initial IDW blending rate (default: the run's, or 5)."""
    tau: float | None = None
    """Initial distance-test ratio; 0 turns the test off (default: the run's, or 1.8)."""
    register_if_missing: bool = True
    """Run the registration (minutes) when the spec's registration file does not exist, and write it there."""
    timeout: float | None = None
    """Stop after this many seconds (default: run until Ctrl+C or SIGTERM)."""

    def main(self) -> None:
        from nerfuser_ns.viewer import start_viewer

        check_device(self.device)
        # The model reads its render-time settings from the environment when it is built.
        if self.blend_method is not None:
            os.environ["NERFUSER_BLEND_METHOD"] = self.blend_method
        if self.gamma is not None:
            os.environ["NERFUSER_GAMMA"] = repr(float(self.gamma))
        if self.tau is not None:
            os.environ["NERFUSER_TAU"] = "none" if self.tau == 0 else repr(float(self.tau))
        # SIGTERM stops as Ctrl+C does: the port and the render threads are released on the way out.
        signal.signal(signal.SIGTERM, _interrupt)
        running = None
        try:
            running = start_viewer(
                self.path,
                host=self.host,
                port=self.port,
                device=self.device,
                max_res=self.max_res,
                register_if_missing=self.register_if_missing,
            )
            names = ", ".join(running.model.nerf_names)
            print(f"nerfuser viewer: {running.url} ({running.model.num_nerfs} NeRFs: {names}); Ctrl+C stops it")
            sys.stdout.flush()
            deadline = None if self.timeout is None else time.monotonic() + self.timeout
            while deadline is None or time.monotonic() < deadline:
                time.sleep(0.2)
        except KeyboardInterrupt:
            pass
        finally:
            if running is not None:
                running.stop()
                print("nerfuser viewer: stopped", flush=True)


def _interrupt(signum: int, frame: object) -> None:
    raise KeyboardInterrupt


def entrypoint() -> None:
    """Entry point of ``ns-nerfuser-view``."""
    from nerfuser_ns.runs import RunLoadError
    from nerfuser_ns.spec import FusionSpecError
    from nerfuser_ns.viewer import ViewerSetupError

    command = tyro.cli(ViewCommand)
    try:
        command.main()
    except (FusionSpecError, RunLoadError, ViewerSetupError) as e:
        ERR_CONSOLE.print(f"[bold red]ns-nerfuser-view: {' '.join(str(e).split())}[/bold red]", highlight=False)
        sys.exit(1)


if __name__ == "__main__":
    entrypoint()

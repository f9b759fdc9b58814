"""``ns-nerfuser-view``: nerfstudio's live viewer on a fused scene, straight from a fusion spec or a fused run.

Example::

    ns-nerfuser-view fusion.json                 # a fusion spec (or its folder, or a registration file)
    ns-nerfuser-view outputs/x/nerfuser/run      # a fused run (what ns-viewer --load-config opens too)

Opens the same viewer as ``ns-viewer --load-config <fused run>/config.yml`` (see :mod:`nerfuser_ns.viewer`) without
``ns-train nerfuser`` first. Serves on the loopback interface by default; pass ``--host 0.0.0.0`` to let other
machines connect. Bad input prints one red line and exits with status 1.
"""

from __future__ import annotations

import shutil
import signal
import socket
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import tyro
from nerfstudio.configs.base_config import ViewerConfig
from nerfstudio.utils import writer
from nerfstudio.viewer.viewer import Viewer
from rich.console import Console
from rich.text import Text

from nerfuser_ns import runs
from nerfuser_ns.adapters import UnsupportedRunError
from nerfuser_ns.blend_choice import BlendChoice
from nerfuser_ns.blend_settings import BlendSettings
from nerfuser_ns.method_configs.nerfuser import nerfuser_config
from nerfuser_ns.model import NerfuserModel, NerfuserModelConfig
from nerfuser_ns.runs import RunLoadError, check_device, default_device
from nerfuser_ns.scripts.cli import parse
from nerfuser_ns.spec import FusionSpecError
from nerfuser_ns.viewer import NerfuserSceneControl, ViewerSetupError

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
    blend_method: BlendChoice | None = None
    """Initial blend method (default: the run's, or auto: idw-sample around objects, idw-2d from a camera rig,
    coverage along a path); the panel changes it live."""
    gamma: float | None = None
    """Initial IDW blending rate (default: the run's, or 5)."""
    tau: float | None = None
    """Initial distance-test ratio; 0 turns the test off (default: the run's, or 1.8)."""
    appearance_matching: bool | None = None
    """Map each NeRF's colours to the reference capture's (default: the run's, or on); the panel switches it live."""
    register_if_missing: bool = True
    """Run the registration (minutes) when the spec's registration file does not exist, and write it there."""
    timeout: float | None = None
    """Stop after this many seconds (default: run until Ctrl+C or SIGTERM)."""

    def main(self) -> None:
        check_device(self.device)
        blend: dict[str, Any] = {}
        if self.blend_method is not None:
            blend["method"] = self.blend_method
        if self.gamma is not None:
            blend["gamma"] = float(self.gamma)
        if self.tau is not None:
            blend["tau"] = None if self.tau == 0 else float(self.tau)
        if self.appearance_matching is not None:
            blend["appearance_matching"] = self.appearance_matching
        try:  # before minutes of loading
            BlendSettings().replace(**blend)
        except ValueError as e:
            raise ViewerSetupError(str(e)) from None
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
                blend=blend,
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


# ----------------------------------------------------------------------------------------------------------------------
# Launching (what ns-nerfuser-view runs; tests start viewers with it too)


@dataclass
class RunningViewer:
    """A viewer started by :func:`start_viewer`; :meth:`stop` closes its port and render threads."""

    viewer: Viewer
    pipeline: Any
    url: str
    """Where a browser opens it (``http://host:port``)."""
    port: int
    step: int
    _tmp_dir: Path | None = None

    @property
    def model(self) -> NerfuserModel:
        return self.pipeline.model

    @property
    def scene_control(self) -> NerfuserSceneControl:
        return self.pipeline.model.viewer_scene

    def stop(self) -> None:
        for machine in list(self.viewer.render_statemachines.values()):
            machine.running = False
        server = self.viewer.viser_server
        if getattr(server._websock_server, "_ws_server", None) is not None:  # not stopped yet
            server.stop()
        if self._tmp_dir is not None:
            shutil.rmtree(self._tmp_dir, ignore_errors=True)
            self._tmp_dir = None


def _is_run(path: Path) -> bool:
    return path.suffix in (".yml", ".yaml") or (path.is_dir() and (path / "config.yml").is_file())


def load_fused_pipeline(
    path: Path | str, device: str | None = None, register_if_missing: bool = True
) -> tuple[Any, Any, int, Path | None]:
    """``(config, pipeline, step, run folder)`` of a fused run (``ns-train nerfuser``'s config.yml or its folder) or
    of a fusion spec (a JSON file, a folder holding fusion.json, or a registration file), in eval mode.

    A spec needs no run folder: the pipeline is the ``nerfuser`` method's, built in memory (run folder None).

    Raises:
        ViewerSetupError, FusionSpecError, RunLoadError: with a one-line message naming the file.
    """
    device = device or runs.default_device()
    path = Path(path).expanduser()
    if not path.exists():
        raise ViewerSetupError(f"{path}: no such file or folder; pass a fused run's config.yml or a fusion spec")
    if _is_run(path):
        config_path = runs.resolve_config_path(path)
        config = runs.read_config(config_path)
        if not isinstance(config.pipeline.model, NerfuserModelConfig):
            raise ViewerSetupError(
                f"{config_path}: a {config.method_name} run, not a fused one; open it with ns-viewer, "
                "or list it under 'runs' in a fusion spec"
            )
        loaded = runs.load_run(config_path, device=device, with_data=True, test_mode="test")
        return loaded.config, loaded.pipeline, loaded.step, loaded.config_path.parent

    data = path.absolute()
    config = nerfuser_config()
    config.pipeline.datamanager.data = data
    config.pipeline.datamanager.register_if_missing = register_if_missing
    config.pipeline.model.fusion_spec = data
    config.machine.device_type = "cuda" if str(device).startswith("cuda") else "cpu"
    pipeline = config.pipeline.setup(device=device, test_mode="test")
    pipeline.eval()
    return config, pipeline, 0, None


def check_bind(host: str, port: int | None) -> None:
    """The viewer can serve on ``host`` and ``port`` (None: a free port is picked later): ViewerSetupError otherwise."""
    if port is not None and not 1 <= port <= 65535:
        raise ViewerSetupError(f"--port {port}: not a TCP port (1-65535)")
    try:
        infos = socket.getaddrinfo(host, port or 0, type=socket.SOCK_STREAM)
    except (socket.gaierror, UnicodeError) as e:
        raise ViewerSetupError(f"--host {host!r}: cannot be resolved ({e}); use 127.0.0.1 or 0.0.0.0") from None
    if port is None:
        return
    family, socktype, proto, _, address = infos[0]
    with socket.socket(family, socktype, proto) as probe:
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            probe.bind(address)
        except OSError as e:
            raise ViewerSetupError(f"cannot serve on {host}:{port} ({e.strerror}); pick another --port") from None


def start_viewer(
    source: Path | str,
    host: str = "127.0.0.1",
    port: int | None = None,
    device: str | None = None,
    max_res: int | None = None,
    register_if_missing: bool = True,
    blend: dict[str, Any] | None = None,
) -> RunningViewer:
    """Open nerfstudio's viewer on a fused run or a fusion spec (see :func:`load_fused_pipeline`); returns at once.

    What ``ns-viewer --load-config`` does, without blocking, on ``host`` (loopback by default) and ``port`` (None:
    7007 or the next free port). ``max_res`` sets the panel's "Max res" (default:
    :data:`nerfuser_ns.viewer.CPU_MAX_RES` on the CPU, nerfstudio's 512 otherwise). ``blend``: initial blend settings
    (``method``, ``gamma``, ``tau``, ``reference_nerf``, ``appearance_matching``) over the run's, through the model's
    ``set_blend``.
    """
    check_bind(host, port)  # viser's server thread dies on a bad bind and the caller would wait forever
    config, pipeline, step, run_dir = load_fused_pipeline(
        source, device=device, register_if_missing=register_if_missing
    )
    if blend:
        try:
            pipeline.model.set_blend(**blend)
        except ValueError as e:
            raise ViewerSetupError(str(e)) from None
    tmp_dir = None
    if run_dir is None:  # the viewer keeps a log file (and its Render tab a config path) beside the run
        tmp_dir = run_dir = Path(tempfile.mkdtemp(prefix="nerfuser-view-"))
    viewer_config = ViewerConfig(
        websocket_host=host, websocket_port=port, num_rays_per_chunk=config.viewer.num_rays_per_chunk
    )
    try:
        viewer = Viewer(
            viewer_config,
            log_filename=run_dir / viewer_config.relative_log_filename,
            datapath=pipeline.datamanager.get_datapath(),
            pipeline=pipeline,
            train_lock=threading.Lock(),
        )
    except BaseException:
        if tmp_dir is not None:
            shutil.rmtree(tmp_dir, ignore_errors=True)
        raise
    if max_res is not None:
        viewer.control_panel._max_res.value = int(max_res)
    # As ns-viewer: no logging, but the writer's buffer must exist (the viewer times its renders into it).
    config.logging.local_writer.enable = False
    writer.setup_local_writer(config.logging, max_iter=config.max_num_iterations)
    viewer.init_scene(
        train_dataset=pipeline.datamanager.train_dataset,
        train_state="completed",
        eval_dataset=pipeline.datamanager.eval_dataset,
    )
    viewer.update_scene(step=step)
    actual_port = int(viewer.viser_server.get_port())
    shown_host = "localhost" if host in ("0.0.0.0", "::") else host
    return RunningViewer(viewer, pipeline, f"http://{shown_host}:{actual_port}", actual_port, step, tmp_dir)


def _interrupt(signum: int, frame: object) -> None:
    raise KeyboardInterrupt


def entrypoint() -> None:
    """Entry point of ``ns-nerfuser-view``."""
    command = parse(ViewCommand)
    try:
        command.main()
    except (FusionSpecError, RunLoadError, ViewerSetupError, UnsupportedRunError) as e:
        # plain text, not console markup: a path like fusion[old].json must print as written
        message = Text(f"ns-nerfuser-view: {' '.join(str(e).split())}", style="bold red")
        ERR_CONSOLE.print(message, highlight=False)
        sys.exit(1)


if __name__ == "__main__":
    entrypoint()

"""The fused scene in nerfstudio's live viewer (viser): how it was put together, and a launcher from a fusion spec.

``ns-viewer --load-config <fused run>/config.yml`` works as for any run: the ``nerfuser`` model carries a
:class:`NerfuserSceneControl` (a nerfstudio ``ViewerControl``), which the viewer sets up when it starts. It adds

* a "NeRFuser" folder at the top of the panel: the blend controls (method, the NeRF shown by ``nerf``, gamma, tau,
  appearance matching; made by :meth:`nerfuser_ns.model.NerfuserModel._add_viewer_controls`), a "Scene overlays"
  checkbox (off) with one toggle per scene group under it, and a legend of the share colours ("Output type"
  ``nerf_share`` shows each NeRF's weight share in its colour);
* the scene groups, hidden until "Scene overlays" is ticked: each NeRF's frame (axes at its origin, one NeRF unit
  long, i.e. scaled by its registered scale, with a sphere in its share colour), the cameras the registration
  rendered from (read from the registration file's ``render_folder``, in each NeRF's colour, grey where the view was
  left out of the SfM) and the test cameras;
* nerfstudio's training controls hidden (Pause/Resume Training, Train Speed, Train Util, the stats line's step:
  nothing trains);
* CPU-friendly render settings (a small maximum resolution, a warmed-up renderer, low-resolution frames sized to the
  renderer's measured speed rather than nerfstudio's 30 fps guess) and an offline page.

:func:`nerfuser_ns.scripts.view.start_viewer` opens the same viewer on a fused run or straight from a fusion spec
(``ns-nerfuser-view``).

Frames: everything is drawn in the common frame, in viser units (nerfstudio's x10, ``VISER_NERFSTUDIO_SCALE_RATIO``).
"""

from __future__ import annotations

import contextlib
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import nerfstudio.configs.base_config  # noqa: F401 - first: nerfstudio.utils.writer imported alone hits nerfstudio's own import cycle
import numpy as np
import viser.theme
import viser.transforms as vtf
from jaxtyping import Float
from nerfstudio.utils import writer
from nerfstudio.utils.writer import GLOBAL_BUFFER, EventName
from nerfstudio.viewer.render_state_machine import RenderAction
from nerfstudio.viewer.viewer_elements import ViewerControl

from nerfuser_ns import runs
from nerfuser_ns.blend_settings import SHARE_PALETTE
from nerfuser_ns.cameras import Intrinsics
from nerfuser_ns.registration.record import read_render_poses, render_folders
from nerfuser_ns.sim3 import transform_poses
from nerfuser_ns.spec import FusionSpecError, read_fusion_spec
from nerfuser_ns.viewer_page import serve_offline_page

if TYPE_CHECKING:  # the model imports this module (it carries the scene control): no import back at run time
    from nerfstudio.viewer.viewer import Viewer

    from nerfuser_ns.model import NerfuserModel
    from nerfuser_ns.spec import FusionSpec

VISER_SCALE = 10.0
"""nerfstudio's viewer draws nerfstudio units x10 (``VISER_NERFSTUDIO_SCALE_RATIO``)."""
CPU_MAX_RES = 256
"""Default "Max res" of the viewer when the model renders on the CPU (nerfstudio's default, 512, takes ~4x longer)."""
LOW_RES_SECONDS = 1.0
"""Longest a low-resolution frame of a fused run (the first ones a browser gets, and those while its camera moves) is
meant to take at the renderer's measured speed; it is then half of "Max res" tall, or less when that would take
longer. nerfstudio sizes them for 30 fps, from a guess of 100k rays/s until it has timed a frame: a 40 px tall first
frame, then ~30 px ones on a CPU."""

# Names of the share colours (nerfuser_ns.blend_settings.SHARE_PALETTE, tab10), for the legend.
_COLOUR_NAMES = ["blue", "orange", "green", "red", "purple", "brown", "pink", "grey", "olive", "cyan"]
_TEST_COLOUR = (255, 211, 105)  # nerfstudio's brand colour: the test cameras
_DROPPED_COLOUR = (140, 140, 140)  # registration views left out of the SfM (too little opacity)


class ViewerSetupError(ValueError):
    """The viewer cannot be opened on this input; the message (one line) names the path and what to do."""


# ----------------------------------------------------------------------------------------------------------------------
# Scene content (plain data: testable without a viewer)


@dataclass
class CameraSet:
    """Cameras in the common frame (camera-to-world, OpenGL axes as nerfstudio)."""

    c2w: Float[np.ndarray, "n 4 4"]
    fov_y: Float[np.ndarray, " n"]
    """Vertical field of view (radians)."""
    aspect: Float[np.ndarray, " n"]
    """Width / height."""
    kept: np.ndarray | None = None
    """Registration views: whether the view went into the SfM (None: all)."""

    def __len__(self) -> int:
        return len(self.c2w)


@dataclass
class NerfFrame:
    """One NeRF of the fusion as drawn: its name, its SIM(3) into the common frame, its registration cameras."""

    name: str
    nerf_to_common: Float[np.ndarray, "4 4"]
    registration_cameras: CameraSet | None = None

    @property
    def scale(self) -> float:
        return float(np.cbrt(np.linalg.det(self.nerf_to_common[:3, :3])))

    @property
    def rotation(self) -> Float[np.ndarray, "3 3"]:
        return self.nerf_to_common[:3, :3] / self.scale

    @property
    def origin(self) -> Float[np.ndarray, "3"]:
        return self.nerf_to_common[:3, 3].copy()


@dataclass
class FusedScene:
    """What :class:`NerfuserSceneControl` draws."""

    nerfs: list[NerfFrame]
    test_cameras: CameraSet | None = None
    notes: list[str] = field(default_factory=list)
    """Why something is missing (e.g. the registration's render folder was deleted); shown once on the console."""


def _camera_set(c2w: np.ndarray, fx: np.ndarray, fy: np.ndarray, width: np.ndarray, height: np.ndarray) -> CameraSet:
    c2w = np.asarray(c2w, dtype=np.float64)
    if c2w.shape[-2] == 3:
        c2w = np.concatenate([c2w, np.broadcast_to([0.0, 0.0, 0.0, 1.0], (*c2w.shape[:-2], 1, 4))], axis=-2)
    n = len(c2w)
    fy = np.broadcast_to(np.asarray(fy, dtype=np.float64).reshape(-1), (n,))
    width = np.broadcast_to(np.asarray(width, dtype=np.float64).reshape(-1), (n,))
    height = np.broadcast_to(np.asarray(height, dtype=np.float64).reshape(-1), (n,))
    return CameraSet(c2w=c2w, fov_y=2 * np.arctan(0.5 * height / fy), aspect=width / height)


def read_render_folder(folder: Path, nerf_to_common: np.ndarray) -> CameraSet:
    """The registration renders of one NeRF (``<render_folder>/poses.json``, written by nerfuser_ns.registration),
    mapped into the common frame.

    Raises:
        ViewerSetupError: the folder or its poses.json is missing or unreadable.
    """
    path = Path(folder) / "poses.json"
    try:
        c2w, kept, intr = read_render_poses(folder)
    except FileNotFoundError:
        raise ViewerSetupError(f"{path}: no such file (the registration's renders were moved or deleted)") from None
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise ViewerSetupError(f"{path}: not a readable poses.json ({type(e).__name__}: {e})") from None
    cams = _camera_set(transform_poses(nerf_to_common, c2w), intr["fx"], intr["fy"], intr["width"], intr["height"])
    cams.kept = kept
    return cams


def short_name(name: str) -> str:
    """A NeRF's name as labelled in the viewer: a run path (older registrations name runs by their config.yml)
    becomes ``experiment/method/timestamp`` (:func:`runs.run_names`)."""
    return runs.run_names([name])[0]


def _same_file(a: Path, b: Path) -> bool:
    try:
        return a.samefile(b)
    except OSError:
        return a.absolute() == b.absolute()


def registration_cameras(spec: FusionSpec) -> tuple[list[CameraSet | None], list[str]]:
    """Per NeRF of the spec, the cameras its registration rendered from (common frame), and notes on what is missing.

    Entries are matched to the spec's NeRFs by run (config.yml), then by name. A hand-written registration (no
    ``render_folder``) has none.
    """
    cams: list[CameraSet | None] = [None] * len(spec.nerfs)
    notes: list[str] = []
    if spec.registration_path is None or not Path(spec.registration_path).is_file():
        return cams, notes
    try:
        entries = render_folders(Path(spec.registration_path))
    except (OSError, ValueError, TypeError, AttributeError) as e:
        return cams, [f"{spec.registration_path}: registration cameras not shown ({type(e).__name__}: {e})"]
    for i, nerf in enumerate(spec.nerfs):
        match = [e for e in entries if e[1] is not None and _same_file(e[1], nerf.config_path)]
        match = match or [e for e in entries if e[0] == nerf.name]
        if not match or match[0][2] is None:
            continue
        try:
            cams[i] = read_render_folder(match[0][2], nerf.nerf_to_common)
        except ViewerSetupError as e:
            notes.append(f"{nerf.name}: registration cameras not shown: {e}")
    return cams, notes


def fused_scene(model: NerfuserModel, datamanager: Any = None) -> FusedScene:
    """What to draw for a fused model: its NeRFs (as rendered), their registration cameras and the test cameras.

    The spec comes from the datamanager (``ns-viewer`` of a fused run, :func:`start_viewer`) or the model's
    ``fusion_spec``; without one (models fused in code) only the NeRF frames are drawn.
    """
    T = model.nerf_to_common.detach().cpu().double().numpy()
    nerfs = [NerfFrame(name, T[i]) for i, name in enumerate(model.nerf_names)]
    scene = FusedScene(nerfs)
    spec = getattr(datamanager, "spec", None)
    if spec is None and getattr(model.config, "fusion_spec", None) is not None:

        try:
            spec = read_fusion_spec(model.config.fusion_spec, register=False)
        except FusionSpecError as e:
            scene.notes.append(f"registration and test cameras not shown: {e}")
    if spec is None:
        return scene
    if [n.name for n in spec.nerfs] == model.nerf_names:
        cams, notes = registration_cameras(spec)
        scene.notes += notes
        for nerf, c in zip(scene.nerfs, cams, strict=True):
            nerf.registration_cameras = c
    else:
        scene.notes.append(f"registration cameras not shown: the model's NeRFs are not those of {spec.spec_path}")
    eval_dataset = getattr(datamanager, "eval_dataset", None)
    if spec.has_test_images and eval_dataset is not None:
        c = eval_dataset.cameras
        scene.test_cameras = _camera_set(
            c.camera_to_worlds.detach().cpu().numpy(),
            c.fx.cpu().numpy(),
            c.fy.cpu().numpy(),
            c.width.cpu().numpy(),
            c.height.cpu().numpy(),
        )
    return scene


# ----------------------------------------------------------------------------------------------------------------------
# The viewer control


def _wxyz(c2w: np.ndarray) -> np.ndarray:
    """viser's orientation of an OpenGL camera-to-world (viser cameras look along +z, OpenGL ones along -z)."""

    R = np.asarray(c2w, dtype=np.float64)[:3, :3]
    u, _, vt = np.linalg.svd(R)  # re-orthonormalise (float32 round trips)
    return (vtf.SO3.from_matrix(u @ vt) @ vtf.SO3.from_x_radians(np.pi)).wxyz


class NerfuserSceneControl(ViewerControl):
    """The NeRFuser panel, scene groups, CPU defaults and an offline page for a fused model in nerfstudio's viewer.

    The model creates it (``model.viewer_scene``); nerfstudio's viewer finds every ``ViewerControl`` of the pipeline
    and calls :meth:`_setup` once it is running. Nothing happens without a viewer.

    ``controls`` (name: nerfstudio ``ViewerElement``) are installed at the top of the panel by :meth:`_setup`. They
    are held here, not by the model: nerfstudio installs every element it finds on the model itself, in a "Custom
    Elements" folder below all of its own controls.
    """

    def __init__(
        self,
        model: NerfuserModel,
        controls: dict[str, Any] | None = None,
        cpu_max_res: int = CPU_MAX_RES,
        warm_up: bool = True,
    ) -> None:
        super().__init__()
        self._model = model
        self.controls: dict[str, Any] = dict(controls or {})
        """The blend controls (``ViewerElement``), by name: blend_method, reference_nerf, gamma, tau,
        appearance_matching."""
        self.cpu_max_res = cpu_max_res
        self.warm_up = warm_up
        self.scene: FusedScene | None = None
        self.groups: dict[str, list[Any]] = {"nerf_frames": [], "registration_cameras": [], "test_cameras": []}
        """Scene handles of each group (what the toggles hide and show)."""
        self.folder: Any = None
        """The panel's "NeRFuser" folder handle."""
        self.overlays: Any = None
        """The "Scene overlays" checkbox handle: shows the groups whose toggle is on (off at start)."""
        self.toggles: dict[str, Any] = {}
        """The panel's checkbox handle of each group (shown while "Scene overlays" is on)."""
        self.axes_lengths: list[float] = []
        """Axes length of each NeRF's frame, in viser units (``VISER_SCALE`` x its registered scale)."""
        self.warm_up_seconds: float | None = None
        self.rays_per_second: float | None = None
        """The renderer's speed, timed after the warm-up (sizes the low-resolution frames; see LOW_RES_SECONDS)."""
        # ns-viewer builds the model before the viser server: the page it serves is fixed now.
        serve_offline_page()

    def _setup(self, viewer: Viewer) -> None:
        super()._setup(viewer)
        model = self._model
        server = viewer.viser_server
        self._offline_theme()
        if model.device.type == "cpu" and self.cpu_max_res:
            viewer.control_panel._max_res.value = min(int(viewer.control_panel.max_res), int(self.cpu_max_res))
        self._hide_training_controls(viewer)
        self.scene = scene = fused_scene(model, getattr(viewer.pipeline, "datamanager", None))
        for note in scene.notes:
            print(f"nerfuser viewer: {note}")
        with server.atomic():
            self._draw(server, scene)
        self._add_panel(viewer, scene)
        server.on_client_connect(self._on_connect)
        if self.warm_up:
            self._warm_up()

    # --- panel ------------------------------------------------------------------------------------------------------

    def _offline_theme(self) -> None:
        """nerfstudio's theme without its title-bar logo (an image fetched from docs.nerf.studio)."""
        buttons = (
            viser.theme.TitlebarButton(text="Getting Started", icon=None, href="https://nerf.studio"),
            viser.theme.TitlebarButton(
                text="Github", icon="GitHub", href="https://github.com/nerfstudio-project/nerfstudio"
            ),
            viser.theme.TitlebarButton(text="Documentation", icon="Description", href="https://docs.nerf.studio"),
        )
        self.viser_server.gui.configure_theme(
            titlebar_content=viser.theme.TitlebarConfig(buttons=buttons, image=None),
            control_layout="collapsible",
            dark_mode=True,
            brand_color=(255, 211, 105),
        )

    @staticmethod
    def _hide_training_controls(viewer: Viewer) -> None:
        """nerfstudio's training controls and the stats line's step: nothing trains in a fused run. (The control panel
        has no public accessor for its Train Speed and Train Util elements; hiding them is ViewerElement's own
        set_hidden.)"""
        for handle in (viewer.pause_train, viewer.resume_train):
            handle.visible = False
        for name in ("_train_speed", "_train_util"):
            element = getattr(viewer.control_panel, name, None)
            if element is not None:
                element.set_hidden(True)
        # the stats line without its training step: nerfstudio rebuilds it through make_stats_markdown
        shown = {"res": "0x0px"}

        def resolution_only(step: int | None, res: str | None) -> str:
            shown["res"] = res if res is not None else shown["res"]
            return f"Resolution: {shown['res']}"

        viewer.make_stats_markdown = resolution_only
        viewer.stats_markdown.content = resolution_only(None, None)

    def _rerender(self) -> None:
        """What nerfstudio does after a change of one of its elements: every browser renders the view again."""
        viewer = self.viewer
        for client_id, client in self.viser_server.get_clients().items():
            machine = viewer.render_statemachines.get(client_id)
            if machine is not None:
                machine.action(RenderAction("rerender", viewer.get_camera_state(client)))

    def _install(self, element: Any) -> None:
        """Install a ViewerElement as nerfstudio installs the model's own: its callback under the viewer's lock, then
        a new render."""
        hook, lock = element.cb_hook, self.viewer.train_lock

        def locked_hook(e: Any) -> None:
            with lock if lock is not None else contextlib.nullcontext():
                hook(e)
            self._rerender()

        element.cb_hook = locked_hook
        element.install(self.viser_server)

    def _sync_controls(self) -> None:
        """The controls' initial values from the model's settings now (they may have changed since the model made
        them, e.g. ``ns-nerfuser-view --gamma``). Before installation a value is only a default: no callback runs."""
        for name, value in self._model.blend_control_values().items():
            if name in self.controls:
                self.controls[name].value = value

    def _add_panel(self, viewer: Viewer, scene: FusedScene) -> None:
        server = viewer.viser_server
        n_reg = sum(len(n.registration_cameras) for n in scene.nerfs if n.registration_cameras is not None)
        n_test = 0 if scene.test_cameras is None else len(scene.test_cameras)
        labels = {
            "nerf_frames": f"NeRF frames ({len(scene.nerfs)})",
            "registration_cameras": f"Registration cameras ({n_reg})",
            "test_cameras": f"Test cameras ({n_test})",
        }
        hints = {
            "nerf_frames": "Each NeRF's axes at its origin, one NeRF unit long (its registered scale)",
            "registration_cameras": "The views the registration rendered (grey: left out of the SfM)",
            "test_cameras": "The fusion spec's test views (test_data or test_run)",
        }
        legend = "  \n".join(
            f"{i}: **{short_name(n.name)}** ({_COLOUR_NAMES[i % len(_COLOUR_NAMES)]}, scale {n.scale:.3g})"
            for i, n in enumerate(scene.nerfs)
        )
        # Above everything nerfstudio put in the panel (its buttons, stats and tabs: viser orders by creation).
        header = [viewer.pause_train, viewer.resume_train, viewer.hide_images, viewer.show_images]
        self.folder = server.gui.add_folder("NeRFuser", order=min(h.order for h in header) - 1.0)
        with self.folder:
            self._sync_controls()
            for element in self.controls.values():
                self._install(element)
            self.overlays = server.gui.add_checkbox(
                "Scene overlays", False, hint="Show how the scene was put together (the groups ticked below)"
            )
            self.overlays.on_update(lambda _: self._show_groups())
            for key, label in labels.items():
                toggle = server.gui.add_checkbox(
                    label, True, hint=hints[key], disabled=not self.groups[key], visible=False
                )
                toggle.on_update(lambda _: self._show_groups())
                self.toggles[key] = toggle
            server.gui.add_markdown(
                "NeRFs (the `nerf_share` output's colours; the `nerf` method shows the reference NeRF):  \n" + legend
            )

    def _show_groups(self) -> None:
        """Each group shown while "Scene overlays" and its own toggle are on; the toggles shown with the overlays."""
        on = bool(self.overlays.value)
        with self.viser_server.atomic():
            for key, toggle in self.toggles.items():
                toggle.visible = on
                for handle in self.groups[key]:
                    handle.visible = on and bool(toggle.value)

    def set_group_visible(self, group: str, visible: bool) -> None:
        """Show or hide one scene group (``nerf_frames``, ``registration_cameras``, ``test_cameras``); showing one
        turns "Scene overlays" on."""
        if group not in self.groups:
            raise KeyError(f"no scene group {group!r}; choose one of {sorted(self.groups)}")
        self.toggles[group].value = bool(visible)
        if visible:
            self.overlays.value = True
        self._show_groups()

    # --- scene ------------------------------------------------------------------------------------------------------

    def _draw(self, server: Any, scene: FusedScene) -> None:
        palette = (SHARE_PALETTE.numpy() * 255).round().astype(int)
        for i, nerf in enumerate(scene.nerfs):
            colour = tuple(int(c) for c in palette[i % len(palette)])
            length = VISER_SCALE * nerf.scale  # one NeRF unit: the NeRF's [-1, 1] box reaches the axes' tips
            base = f"/nerfuser/nerf_frames/{i}"
            frame = server.scene.add_frame(
                base,
                wxyz=_frame_wxyz(nerf.rotation),
                position=nerf.origin * VISER_SCALE,
                axes_length=length,
                axes_radius=0.02 * length,
                visible=False,  # every group starts hidden ("Scene overlays" shows them)
            )
            self.axes_lengths.append(length)
            dot = server.scene.add_icosphere(f"{base}/origin", radius=0.06 * length, color=colour, visible=False)
            label = server.scene.add_label(f"{base}/name", text=f"{i}: {short_name(nerf.name)}", visible=False)
            self.groups["nerf_frames"] += [frame, dot, label]
            cams = nerf.registration_cameras
            if cams is not None:
                for k in range(len(cams)):
                    kept = cams.kept is None or bool(cams.kept[k])
                    self.groups["registration_cameras"].append(
                        server.scene.add_camera_frustum(
                            f"/nerfuser/registration_cameras/{i}/{k:05d}",
                            fov=float(cams.fov_y[k]),
                            aspect=float(cams.aspect[k]),
                            scale=0.04 * length,
                            color=colour if kept else _DROPPED_COLOUR,
                            wxyz=_wxyz(cams.c2w[k]),
                            position=cams.c2w[k][:3, 3] * VISER_SCALE,
                            visible=False,
                        )
                    )
        if scene.test_cameras is not None:
            cams = scene.test_cameras
            size = 0.04 * VISER_SCALE * (np.median([n.scale for n in scene.nerfs]) if scene.nerfs else 1.0)
            for k in range(len(cams)):
                self.groups["test_cameras"].append(
                    server.scene.add_camera_frustum(
                        f"/nerfuser/test_cameras/{k:05d}",
                        fov=float(cams.fov_y[k]),
                        aspect=float(cams.aspect[k]),
                        scale=float(size),
                        color=_TEST_COLOUR,
                        wxyz=_wxyz(cams.c2w[k]),
                        position=cams.c2w[k][:3, 3] * VISER_SCALE,
                        visible=False,
                    )
                )

    def start_view(self) -> tuple[np.ndarray, np.ndarray] | None:
        """Where a new browser tab starts, ``(position, look_at)`` in the common frame: a little behind the first test
        camera (else the reference NeRF's first registration view the SfM kept), looking where it looks; without
        cameras, the NeRF origins from above. Not AT a camera: its frustum and image would cover the render."""
        scene = self.scene
        if scene is None or not scene.nerfs:
            return None
        unit = float(np.median([n.scale for n in scene.nerfs]))  # NeRF units in common units
        c2w = None
        if scene.test_cameras is not None and len(scene.test_cameras):
            c2w = scene.test_cameras.c2w[0]
        else:
            for nerf in scene.nerfs:
                cams = nerf.registration_cameras
                if cams is not None and len(cams):
                    kept = np.flatnonzero(cams.kept) if cams.kept is not None else np.arange(len(cams))
                    c2w = cams.c2w[kept[0] if len(kept) else 0]
                    break
        if c2w is None:
            centre = np.mean([n.origin for n in scene.nerfs], axis=0)
            return centre + unit * np.array([1.5, -1.5, 1.0]), centre
        back = c2w[:3, 2] / np.linalg.norm(c2w[:3, 2])  # OpenGL cameras look along -z
        return c2w[:3, 3] + 0.15 * unit * back, c2w[:3, 3] - unit * back

    def _on_connect(self, client: Any) -> None:
        self._initial_view(client)
        self._size_low_res_frames(client)

    def _initial_view(self, client: Any) -> None:
        view = self.start_view()
        if view is None:
            return
        position, look_at = view
        with client.atomic():
            client.camera.position = position * VISER_SCALE
            client.camera.look_at = look_at * VISER_SCALE

    def _size_low_res_frames(self, client: Any) -> None:
        """On the CPU, a browser's low-resolution frames (its first ones, and those while its camera moves) as large
        as :data:`LOW_RES_SECONDS` allows at the measured speed, up to half of "Max res".

        nerfstudio's render state machine (one per browser, made just before this runs) sizes them to
        ``rays/s / target_fps`` rays, with its 30 fps target and, until it has timed a frame of its own, 100k rays/s:
        a GPU's speed. The warm-up's timing goes into the same record (nerfstudio's writer buffer) and the machine's
        ``target_fps`` is lowered to fit. On a GPU nerfstudio's defaults stay."""

        machine = self.viewer.render_statemachines.get(client.client_id)
        if self._model.device.type != "cpu" or machine is None or not self.rays_per_second:
            return
        if not writer.is_initialized():
            return  # nerfstudio keeps no timings then: its 100k rays/s guess stays
        key = EventName.VIS_RAYS_PER_SEC.value
        if key not in GLOBAL_BUFFER["events"]:
            writer.put_time(name=EventName.VIS_RAYS_PER_SEC, duration=self.rays_per_second, step=self.viewer.step)
        rate = GLOBAL_BUFFER["events"][key]["avg"]
        half_res_rays = client.camera.aspect * (self.viewer.control_panel.max_res / 2) ** 2
        machine.target_fps = float(np.clip(rate / half_res_rays, 1.0 / LOW_RES_SECONDS, machine.target_fps))

    def _warm_up(self) -> None:
        """Two small renders before the first browser tab connects: the first pays the one-off costs (the CPU fast
        path's compile, lazy allocations), so that a browser's first frame comes within a second or two; the second
        times the renderer (:attr:`rays_per_second`)."""

        model = self._model
        c2w = np.eye(4)  # any view: rays cost about the same wherever they look
        c2w[:3, 3] = model.nerf_origins[0].detach().cpu().numpy() + [0.0, 0.0, float(model.nerf_scales[0])]

        def render(width: int, height: int) -> None:
            cams = runs.make_cameras(c2w[None, :3, :], Intrinsics(width, width, width / 2, height / 2, width, height))
            runs.render_views(model, cams.to(model.device), outputs=("rgb",), progress=False)  # returns CPU tensors

        try:
            start = time.perf_counter()
            render(8, 8)
            self.warm_up_seconds = time.perf_counter() - start
            start = time.perf_counter()
            render(48, 32)
            self.rays_per_second = 48 * 32 / max(time.perf_counter() - start, 1e-6)
        except Exception as e:  # noqa: BLE001 - the viewer's own first render will show the error
            print(f"nerfuser viewer: warm-up render failed ({type(e).__name__}: {e})")


def _frame_wxyz(rotation: np.ndarray) -> np.ndarray:
    """viser's orientation of a frame with the given rotation (axes: no camera flip)."""

    u, _, vt = np.linalg.svd(np.asarray(rotation, dtype=np.float64))
    return vtf.SO3.from_matrix(u @ vt).wxyz

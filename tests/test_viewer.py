"""The live viewer on a fused scene, seen by a real browser.

A headless Debian chromium (installed by scripts/setup_browser.sh) loads the viewer's page over loopback and is
driven through the DevTools protocol (websocket-client, no browser-driver package): screenshots must show the
blended render the viewer sent, and controls changed through the viewer's API must change the next frame. The fused
scene is the two shipped demo NeRFs (demo/runs), registered as ``make demo`` registered them, in a common frame
scaled by 1.5 so that registered scales differ from 1.
"""

from __future__ import annotations

import base64
import io
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
import urllib.request
from pathlib import Path

import numpy as np
import pytest
import torch
import websocket
from nerfstudio.viewer import render_state_machine
from PIL import Image

from nerfuser_ns import registration, sim3
from nerfuser_ns.blend_settings import SHARE_PALETTE as _PALETTE
from nerfuser_ns.data import PlaceholderImageDataset
from nerfuser_ns.renderers import RenderBatch
from nerfuser_ns.scripts.view import ViewCommand, check_bind, load_fused_pipeline, start_viewer
from nerfuser_ns.spec import write_fusion_spec
from nerfuser_ns.viewer import LOW_RES_SECONDS, VISER_SCALE, ViewerSetupError

pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent
RUNS = [ROOT / "demo" / "runs" / c / "nerfacto-cpu" / "demo" / "config.yml" for c in ("capture_a", "capture_b")]
MAX_RES = 96  # small "high" frames keep the test short on a 2-core machine
WINDOW = (1280, 720)


def _orthonormal_sim3(T: np.ndarray) -> np.ndarray:
    u, s, vt = np.linalg.svd(T[:3, :3])
    return sim3.make_sim3(u @ vt, T[:3, 3], float(np.cbrt(np.prod(s))))


# capture_b's frame in capture_a's, as `make demo` estimated it (rounded)
T_B_TO_A = _orthonormal_sim3(
    np.array(
        [
            [0.368978, 0.929251, 0.016125, 0.135515],
            [-0.929384, 0.368988, 0.002446, 1.08786],
            [-0.003677, -0.015889, 0.999823, 0.035184],
            [0.0, 0.0, 0.0, 1.0],
        ]
    )
)
# the common frame: capture_a's, scaled by 1.5 and moved
A_TO_COMMON = sim3.make_sim3(np.eye(3), np.array([0.3, -0.2, 0.1]), 1.5)
TRANSFORMS = [A_TO_COMMON, A_TO_COMMON @ T_B_TO_A]


# ----------------------------------------------------------------------------------------------------------------------
# A headless browser over the DevTools protocol


def chromium_path() -> str:
    for candidate in (os.environ.get("NERFUSER_CHROMIUM"), shutil.which("chromium"), shutil.which("chromium-browser")):
        if candidate and os.access(candidate, os.X_OK):
            return candidate
    pytest.fail("no chromium for the viewer test: run scripts/setup_browser.sh (as root) or set NERFUSER_CHROMIUM")


class HeadlessChromium:
    """One headless chromium page, driven over the DevTools protocol; records every request the page makes."""

    def __init__(self, width: int, height: int) -> None:
        self.profile = Path(tempfile.mkdtemp(prefix="nerfuser-chromium-"))
        self.proc = subprocess.Popen(
            [
                chromium_path(),
                "--headless=new",
                "--no-sandbox",  # CI runs as root
                "--use-angle=swiftshader",  # WebGL in software: no GPU here
                "--enable-unsafe-swiftshader",
                "--disable-background-networking",  # the browser's own calls home: none, the page's own are checked
                "--disable-component-update",
                "--disable-sync",
                "--no-first-run",
                "--no-default-browser-check",
                "--remote-debugging-address=127.0.0.1",
                "--remote-debugging-port=0",
                f"--user-data-dir={self.profile}",
                f"--window-size={width},{height}",
                "about:blank",
            ],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
            start_new_session=True,  # its helper processes share its process group: closed together
        )
        self.messages: list[dict] = []
        self._id = 0
        port_file = self.profile / "DevToolsActivePort"
        deadline = time.monotonic() + 60
        while not (port_file.is_file() and port_file.read_text().strip()):
            if self.proc.poll() is not None or time.monotonic() > deadline:
                self.close()
                pytest.fail(f"chromium did not start (exit status {self.proc.returncode})")
            time.sleep(0.1)
        port = port_file.read_text().split()[0]
        pages = json.loads(urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=10).read())
        self.ws = websocket.create_connection(
            next(p for p in pages if p["type"] == "page")["webSocketDebuggerUrl"], timeout=60
        )
        self.call("Network.enable")
        self.call("Page.enable")
        self.call("Emulation.setDeviceMetricsOverride", width=width, height=height, deviceScaleFactor=1, mobile=False)

    def call(self, method: str, **params) -> dict:
        self._id += 1
        self.ws.send(json.dumps({"id": self._id, "method": method, "params": params}))
        while True:
            message = json.loads(self.ws.recv())
            if message.get("id") == self._id:
                assert "error" not in message, message
                return message["result"]
            self.messages.append(message)

    def screenshot(self) -> np.ndarray:
        data = self.call("Page.captureScreenshot", format="png")["data"]
        return np.asarray(Image.open(io.BytesIO(base64.b64decode(data))).convert("RGB"))

    def canvas_box(self) -> tuple[int, int, int, int]:
        """(x0, y0, x1, y1) of the viewer's 3D canvas in the page."""
        expr = "JSON.stringify(document.querySelector('canvas').getBoundingClientRect())"
        box = json.loads(self.call("Runtime.evaluate", expression=expr)["result"]["value"])
        return int(box["left"]), int(box["top"]), int(box["right"]), int(box["bottom"])

    def requested_urls(self) -> list[str]:
        return [m["params"]["request"]["url"] for m in self.messages if m.get("method") == "Network.requestWillBeSent"]

    def outside_requests(self) -> list[str]:
        """What the page asked for beyond this machine's loopback (the viewer must work offline)."""
        local = ("http://127.0.0.1:", "ws://127.0.0.1:", "blob:", "data:", "about:")
        return [u for u in self.requested_urls() if not u.startswith(local)]

    def close(self) -> None:
        ws = getattr(self, "ws", None)
        if ws is not None:
            ws.close()
        if self.proc.poll() is None:
            os.killpg(self.proc.pid, signal.SIGTERM)
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                os.killpg(self.proc.pid, signal.SIGKILL)
                self.proc.wait(10)
        shutil.rmtree(self.profile, ignore_errors=True)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def port_closed(port: int, within: float = 10.0) -> bool:
    deadline = time.monotonic() + within
    while time.monotonic() < deadline:
        try:
            socket.create_connection(("127.0.0.1", port), timeout=1).close()
        except OSError:
            return True
        time.sleep(0.2)
    return False


def wait_for(predicate, timeout: float, what: str, step: float = 0.25):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(step)
    pytest.fail(f"timed out after {timeout:.0f} s waiting for {what}")


def resized(image: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    return np.asarray(Image.fromarray(image).resize(size, Image.BILINEAR), dtype=np.float32) / 255


def correlation(a: np.ndarray, b: np.ndarray) -> float:
    a, b = a.ravel() - a.mean(), b.ravel() - b.mean()
    return float(a @ b / (np.linalg.norm(a) * np.linalg.norm(b) + 1e-12))


# ----------------------------------------------------------------------------------------------------------------------
# The fused scene


class PosesOnly:
    """A registration renderer that renders nothing worth seeing: only the render folder's poses matter here.

    The last view sees nothing (zero accumulation), so the registration leaves it out of the SfM.
    """

    def __init__(self, name: str) -> None:
        self.name = name

    def cache_key(self) -> str:
        return f"poses-only:{self.name}"

    def render(self, c2w, intrinsics) -> RenderBatch:
        n, h, w = len(c2w), intrinsics.height, intrinsics.width
        acc = np.ones((n, h, w), np.float32)
        if np.allclose(c2w[-1], self.last):
            acc[-1] = 0.0
        return RenderBatch(np.full((n, h, w, 3), 0.5, np.float32), acc)

    def training_poses(self):
        return None


NUM_POSES = 6


@pytest.fixture(scope="module")
def fusion_spec(tmp_path_factory) -> Path:
    """Spec of the two demo NeRFs: a registration file whose render folders hold 6 views each, 3 test views."""
    root = tmp_path_factory.mktemp("fusion")
    sampling = registration.PoseSamplingConfig(source="hemisphere", num_poses=NUM_POSES, width=8, height=6)
    nerfs = []
    for name, config, T in zip(("a", "b"), RUNS, TRANSFORMS, strict=True):
        renderer = PosesOnly(name)
        renderer.last = registration.sample_poses(renderer, sampling)[0][-1]
        views = registration.render_views_cached(renderer, sampling, root / "registration_work" / "renders")
        nerfs.append(
            {"name": name, "config": str(config), "T_to_reference": T.tolist(), "render_folder": str(views.folder)}
        )
    (root / "registration.json").write_text(json.dumps({"kind": "nerfuser_registration", "nerfs": nerfs}))
    # test views: a's first three registration views, in the common frame
    poses = json.loads((Path(nerfs[0]["render_folder"]) / "poses.json").read_text())["views"]
    test_c2w = sim3.transform_poses(A_TO_COMMON, np.array([v["c2w"] for v in poses[:3]]))
    (root / "test" / "images").mkdir(parents=True)
    frames = []
    for i, c2w in enumerate(test_c2w):
        Image.fromarray(np.full((6, 8, 3), 60 * i, np.uint8)).save(root / "test" / "images" / f"{i}.png")
        frames.append({"file_path": f"images/{i}.png", "transform_matrix": c2w.tolist()})
    meta = {"camera_model": "OPENCV", "fl_x": 7.0, "fl_y": 7.0, "cx": 4.0, "cy": 3.0, "w": 8, "h": 6, "frames": frames}
    (root / "test" / "transforms.json").write_text(json.dumps(meta))
    return write_fusion_spec(root / "fusion.json", RUNS, registration="registration.json", test_data="test")


# ----------------------------------------------------------------------------------------------------------------------
# In-process viewer + browser


class FrameLog:
    """Every image the viewer sends to the browser, with the render state and the model's settings at the time."""

    def __init__(self) -> None:
        self.frames: list[dict] = []
        self.connected_at: float | None = None

    def install(self, monkeypatch: pytest.MonkeyPatch) -> None:
        original = render_state_machine.RenderStateMachine._send_output_to_viewer
        log = self

        def recording(machine, outputs, static_render=True):
            result = original(machine, outputs, static_render)
            model = machine.viewer.get_model()
            log.frames.append(
                {
                    "time": time.monotonic(),
                    "state": machine.state,
                    "image": log.last_image,
                    "output": machine.viewer.control_panel.output_render,
                    "method": model.active_method,  # auto resolved
                    "reference": model.reference_nerf,
                }
            )
            return result

        def set_background_image(scene_api, image, *args, **kwargs):
            log.last_image = np.array(image)
            return original_bg(scene_api, image, *args, **kwargs)

        import viser._scene_api

        original_bg = viser._scene_api.SceneApi.set_background_image
        monkeypatch.setattr(render_state_machine.RenderStateMachine, "_send_output_to_viewer", recording)
        monkeypatch.setattr(viser._scene_api.SceneApi, "set_background_image", set_background_image)

    def after(self, t: float, state: str | None = None, **settings) -> dict | None:
        for f in self.frames:
            if f["time"] > t and (state is None or f["state"] == state) and all(f[k] == v for k, v in settings.items()):
                return f
        return None


@pytest.fixture(scope="module")
def browser():
    browser = HeadlessChromium(*WINDOW)
    yield browser
    browser.close()
    assert browser.proc.returncode is not None


@pytest.fixture(scope="module")
def session(fusion_spec, browser):
    """The viewer started in this process on the spec (as ns-nerfuser-view does), with the browser on its page."""
    torch.set_num_threads(1)
    log = FrameLog()
    port = free_port()
    with pytest.MonkeyPatch.context() as mp:
        log.install(mp)
        started = time.monotonic()
        running = start_viewer(fusion_spec, host="127.0.0.1", port=port, max_res=MAX_RES)
        startup_s = time.monotonic() - started
        running.viewer.viser_server.on_client_connect(lambda client: setattr(log, "connected_at", time.monotonic()))
        try:
            browser.call("Page.navigate", url=running.url)
            yield {"running": running, "browser": browser, "log": log, "startup_s": startup_s}
        finally:
            browser.call("Page.navigate", url="about:blank")
            running.stop()
            assert port_closed(running.port), f"port {running.port} still open after stop()"


def canvas_image(browser: HeadlessChromium) -> np.ndarray:
    x0, y0, x1, y1 = browser.canvas_box()
    return browser.screenshot()[y0:y1, x0:x1]


def shows(browser: HeadlessChromium, frame: np.ndarray) -> float:
    """How well the page matches a frame the viewer sent: the correlation of the two, where the frame is shown (the
    canvas, left of the panel that floats on its right: the frame's aspect ratio)."""
    shot = canvas_image(browser)
    h, w = frame.shape[:2]
    shown = shot[:, : round(shot.shape[0] * w / h)]
    size = (max(w // 3, 8), max(h // 3, 8))  # coarser than the frame: JPEG and the browser's upscaling differ
    return correlation(resized(shown, size), resized(frame, size))


def test_page_shows_the_blended_render_low_resolution_first(session, tmp_path):
    running, browser, log = session["running"], session["browser"], session["log"]
    control = running.scene_control
    # the scene overlays start hidden (before any browser could change them)
    assert control.overlays.value is False
    assert not any(h.visible for g in control.groups.values() for h in g)
    assert not any(t.visible for t in control.toggles.values())
    wait_for(lambda: log.connected_at, 60, "the browser to connect")
    high = wait_for(lambda: log.after(0, state="high"), 120, "a full-resolution frame")
    first = log.frames[0]
    low = [f for f in log.frames if f["time"] < high["time"]]
    sizes = " ".join(f"{f['image'].shape[1]}x{f['image'].shape[0]}" for f in low)
    print(
        f"\nviewer start {session['startup_s']:.1f} s (warm-up {control.warm_up_seconds:.1f} s, "
        f"{control.rays_per_second:.0f} rays/s); low-resolution frames {sizes}, "
        f"the first {first['time'] - log.connected_at:.1f} s after the browser connected, "
        f"{high['image'].shape[1]}x{high['image'].shape[0]} after {high['time'] - log.connected_at:.1f} s"
    )
    assert first["time"] - log.connected_at < 30
    assert first["image"].shape[0] < high["image"].shape[0] and max(high["image"].shape[:2]) == MAX_RES
    # Low-resolution frames: half of Max res tall, or what LOW_RES_SECONDS allows at the measured speed; not
    # nerfstudio's 30 fps sizing from a 100k rays/s guess (40 px, then its 30 px floor on a CPU).
    machine = next(iter(running.viewer.render_statemachines.values()))
    assert machine.target_fps < 30
    aspect = high["image"].shape[1] / high["image"].shape[0]
    floor = min(MAX_RES / 2, np.sqrt(control.rays_per_second * LOW_RES_SECONDS / aspect)) - 10  # rounded to tens
    # the first frame is sized by that; later ones by nerfstudio's own timing of the frames before, which a busy
    # machine (another test process beside this one) can shrink to its 30 px floor
    assert low[0]["image"].shape[0] >= floor, ([f["image"].shape for f in low], floor)
    assert all(f["image"].shape[0] >= 30 for f in low), [f["image"].shape for f in low]
    frame = high["image"].astype(np.float32) / 255
    assert frame.std() > 0.08 and np.ptp(frame.reshape(-1, 3), axis=0).min() > 0.3  # a scene, not a flat colour

    # the panel: NeRFuser's controls first, nerfstudio's training controls hidden (server side, then on the page)
    viewer = running.viewer
    assert not viewer.pause_train.visible and not viewer.resume_train.visible
    panel = viewer.control_panel
    assert not panel._train_speed.gui_handle.visible and not panel._train_util.gui_handle.visible
    assert control.folder.order < min(h.order for h in (viewer.pause_train, viewer.hide_images, viewer.stats_markdown))
    text = wait_for(lambda: (t := page_text(browser)) and "NeRFuser blend method" in t and t, 30, "the panel")
    assert text.index("NeRFuser blend method") < text.index("Hide Train Cams") < text.index("Render Options")
    for label in ("NeRFuser reference NeRF", "NeRFuser gamma", "NeRFuser tau (0: off)", "Scene overlays"):
        assert text.index(label) < text.index("Hide Train Cams"), label
    for hidden in ("Pause Training", "Resume Training", "Train Speed", "Train Util", "Custom Elements", "NeRF frames",
                   "Step:"):  # fmt: skip
        assert hidden not in text, hidden
    assert viewer.stats_markdown.content.startswith("Resolution: ") and "0x0px" not in viewer.stats_markdown.content

    # hide what is still drawn over the render: nerfstudio's test-image frustums
    running.viewer.set_camera_visibility(False)
    time.sleep(1.5)
    match = wait_for(lambda: (c := shows(browser, log.frames[-1]["image"])) > 0.9 and c, 30, "the page to show it")
    print(f"screenshot vs. the frame sent: correlation {match:.3f}")
    shot = canvas_image(browser)
    Image.fromarray(browser.screenshot()).save(tmp_path / "page.png")  # for a person to look at
    Image.fromarray(log.frames[-1]["image"]).save(tmp_path / "frame.png")
    print(f"page and frame: {tmp_path}")
    assert shot.astype(np.float32).std() / 255 > 0.08

    assert not browser.outside_requests(), f"the page made outside requests: {browser.outside_requests()}"


def test_controls_change_the_next_frame(session):
    running, browser, log = session["running"], session["browser"], session["log"]
    model, controls = running.model, running.scene_control.controls
    assert model.blend_method == "auto"  # the default
    first = model.active_method
    before = wait_for(lambda: log.after(0, state="high", method=first, output="rgb"), 120, "a first frame")
    changed = time.monotonic()
    assert controls["reference_nerf"].options == [f"{i}: {n}" for i, n in enumerate(model.nerf_names)]
    controls["reference_nerf"].value = controls["reference_nerf"].options[1]
    controls["blend_method"].value = "nerf"  # NeRF b alone
    after = wait_for(lambda: log.after(changed, state="high", method="nerf", reference=1), 120, "a new frame")
    diff = np.abs(after["image"].astype(np.float32) - before["image"].astype(np.float32)).mean() / 255
    print(f"\n{before['method']} -> nerf (b): mean |difference| {diff:.3f}")
    assert diff > 0.03
    wait_for(lambda: shows(browser, after["image"]) > 0.9, 30, "the page to show the new frame")
    assert shows(browser, after["image"]) > shows(browser, before["image"]) + 0.1

    # the share output: b alone has all the weight, so every pixel is b's colour
    changed = time.monotonic()
    running.viewer.control_panel._output_render.value = "nerf_share"
    share = wait_for(lambda: log.after(changed, state="high", output="nerf_share"), 120, "a share frame")
    orange = _PALETTE[1].numpy()
    np.testing.assert_allclose(share["image"].reshape(-1, 3).mean(0) / 255, orange, atol=0.03)
    # blended again: both colours appear, in proportion to the shares
    changed = time.monotonic()
    controls["blend_method"].value = "idw-sample"
    mixed = wait_for(lambda: log.after(changed, state="high", output="nerf_share", method="idw-sample"), 120, "mix")
    pixels = mixed["image"].reshape(-1, 3).astype(np.float32) / 255
    blue = _PALETTE[0].numpy()
    share_a = ((pixels - orange) @ (blue - orange) / ((blue - orange) @ (blue - orange))).clip(0, 1)
    assert share_a.mean() > 0.05 and share_a.mean() < 0.95, share_a.mean()
    running.viewer.control_panel._output_render.value = "rgb"


def test_scene_groups_show_how_the_scene_was_put_together(session):
    running = session["running"]
    control = running.scene_control
    scene = control.scene
    assert [n.name for n in scene.nerfs] == ["a", "b"]
    frames = control.groups["nerf_frames"][::3]  # frame, origin sphere, label per NeRF
    for frame, length, T in zip(frames, control.axes_lengths, TRANSFORMS, strict=True):
        np.testing.assert_allclose(frame.position, T[:3, 3] * VISER_SCALE, atol=1e-5)
        assert length == pytest.approx(VISER_SCALE * np.cbrt(np.linalg.det(T[:3, :3])), rel=1e-5)  # 15: scale 1.5
    assert control.axes_lengths[0] == pytest.approx(15.0)
    # registration cameras: every rendered view, in the common frame; the one left out of the SfM is grey
    reg = control.groups["registration_cameras"]
    assert len(reg) == 2 * NUM_POSES
    cams_b = scene.nerfs[1].registration_cameras
    assert cams_b.kept.tolist() == [True] * (NUM_POSES - 1) + [False]
    hemisphere = registration.PoseSamplingConfig(source="hemisphere", num_poses=NUM_POSES)
    poses_b = registration.sample_poses(PosesOnly("b"), hemisphere)[0]
    np.testing.assert_allclose(cams_b.c2w, sim3.transform_poses(TRANSFORMS[1], poses_b), atol=1e-6)
    np.testing.assert_allclose(reg[NUM_POSES].position, cams_b.c2w[0][:3, 3] * VISER_SCALE, atol=1e-4)
    assert len(control.groups["test_cameras"]) == 3
    # one checkbox shows every group, and the toggles of each; each group then toggles on its own
    every = [h for g in control.groups.values() for h in g]
    control.overlays.value = True
    wait_for(lambda: all(h.visible for h in every), 10, "every group to show")
    assert all(t.visible for t in control.toggles.values())
    control.toggles["registration_cameras"].value = False
    wait_for(lambda: not any(h.visible for h in reg), 10, "the registration cameras to hide")
    assert all(h.visible for h in control.groups["nerf_frames"] + control.groups["test_cameras"])
    control.toggles["registration_cameras"].value = True
    wait_for(lambda: all(h.visible for h in reg), 10, "the registration cameras to show")
    control.overlays.value = False
    wait_for(lambda: not any(h.visible for h in every), 10, "every group to hide")
    assert not any(t.visible for t in control.toggles.values())


# ----------------------------------------------------------------------------------------------------------------------
# The commands


class Command:
    """A long-running command in its own process group; its output is collected line by line."""

    def __init__(self, cmd: list[str], cwd: Path) -> None:
        env = {**os.environ, "OMP_NUM_THREADS": "1"}
        self.proc = subprocess.Popen(
            cmd, cwd=cwd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, start_new_session=True
        )
        self.lines: list[str] = []
        self._reader = threading.Thread(target=lambda: self.lines.extend(self.proc.stdout), daemon=True)
        self._reader.start()

    def line(self, prefix: str) -> str | None:
        return next((line for line in list(self.lines) if line.startswith(prefix)), None)

    def stop(self) -> str:
        """SIGTERM, as a service manager or Ctrl+C would stop it; the whole output."""
        if self.proc.poll() is None:
            os.killpg(self.proc.pid, signal.SIGTERM)
        try:
            self.proc.wait(30)
        except subprocess.TimeoutExpired:
            os.killpg(self.proc.pid, signal.SIGKILL)
            self.proc.wait(10)
        self._reader.join(10)
        return "".join(self.lines)


def fuse(spec: Path, experiment: str) -> Path:
    """`ns-train nerfuser` on a spec: the fused run's config.yml, which ns-viewer loads."""
    out = spec.parent / "outputs"
    proc = subprocess.run(
        [str(BIN / "ns-train"), "nerfuser", "--data", str(spec), "--output-dir", str(out)]
        + ["--experiment-name", experiment, "--timestamp", "run"],
        cwd=spec.parent,
        env={**os.environ, "OMP_NUM_THREADS": "1"},
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    return out / experiment / "nerfuser" / "run" / "config.yml"


@pytest.fixture(scope="module")
def fused_run(fusion_spec) -> Path:
    """A run fused from the runs alone, as a user fuses their own (no test_data): nerfstudio's viewer reads every
    attribute of the pipeline, the eval loader included, and must still serve the scene."""
    spec = write_fusion_spec(fusion_spec.parent / "fusion_no_test.json", RUNS, registration="registration.json")
    return fuse(spec, "fused_no_test")


def page_text(browser: HeadlessChromium) -> str:
    return browser.call("Runtime.evaluate", expression="document.body.innerText")["result"].get("value", "")


def ns_viewer(config: Path) -> tuple[Command, int]:
    """nerfstudio's own ``ns-viewer`` on a fused run, once it serves and has set up (our control included): the
    banner comes just before the first render."""
    port = free_port()
    command = Command(
        [str(BIN / "ns-viewer"), "--load-config", str(config)]
        + ["--viewer.websocket-host", "127.0.0.1", "--viewer.websocket-port", str(port)],
        config.parent,
    )
    try:
        wait_for(lambda: command.line("[") and _get(f"http://127.0.0.1:{port}/"), 180, "ns-viewer to serve", 0.5)
        wait_for(lambda: any("disabled local writer" in line for line in command.lines), 120, "ns-viewer setup", 0.5)
    except BaseException:
        command.stop()
        raise
    return command, port


def test_ns_viewer_shows_a_fused_run(fused_run, browser):
    """nerfstudio's own command on the fused run (no test images): the page shows the blended render and the NeRFuser
    panel."""
    command, port = ns_viewer(fused_run)
    try:
        browser.call("Page.navigate", url=f"http://127.0.0.1:{port}/")
        text = wait_for(
            lambda: (t := page_text(browser)) and "Resolution:" in t and "0x0px" not in t and t, 60, "a first frame"
        )
        # NeRFuser's panel first, its scene groups' toggles shown with the overlays only, no training controls
        for label in ("NeRFuser blend method", "NeRFuser gamma", "NeRFuser tau", "NeRFuser reference NeRF",
                      "Scene overlays"):  # fmt: skip
            assert label in text and text.index(label) < text.index("Render Options"), label
        for label in ("NeRF frames (2)", "Pause Training", "Train Speed", "Train Util", "Custom Elements", "Step:"):
            assert label not in text, label
        shot = canvas_image(browser)
        assert shot.astype(np.float32).std() / 255 > 0.08  # an image, not the empty dark scene
        assert not browser.outside_requests(), f"the page made outside requests: {browser.outside_requests()}"
    finally:
        browser.call("Page.navigate", url="about:blank")
        out = command.stop()
    assert command.proc.returncode in (0, -signal.SIGTERM), out[-3000:]
    assert "Traceback" not in out and "no test images" not in out, out[-3000:]
    assert port_closed(port)


def test_ns_nerfuser_view_serves_a_fused_run_and_stops_cleanly(fused_run, tmp_path):
    port = free_port()
    command = Command([str(BIN / "ns-nerfuser-view"), str(fused_run.parent), "--port", str(port)], tmp_path)
    try:
        ready = wait_for(lambda: command.line("nerfuser viewer: http"), 180, "ns-nerfuser-view to start", 0.5)
        assert ready.startswith(f"nerfuser viewer: http://127.0.0.1:{port} (2 NeRFs: a, b)"), ready
        page = _get(f"http://127.0.0.1:{port}/")
        assert page is not None and '<div id="root">' in page and "googletagmanager" not in page  # the offline page
    finally:
        out = command.stop()
    assert command.proc.returncode == 0, out[-3000:]
    assert "nerfuser viewer: stopped" in out
    assert port_closed(port)


def _get(url: str) -> str | None:
    try:
        return urllib.request.urlopen(url, timeout=2).read().decode()
    except OSError:
        return None


def test_viewer_opens_a_registration_file_without_test_images(fusion_spec):
    """The common case of a user fusing their own runs: no test images. nerfstudio's viewer reads every attribute
    of the pipeline; the datamanager's eval loader must not raise there."""
    running = start_viewer(fusion_spec.parent / "registration.json", host="127.0.0.1", port=free_port(),
                           blend={"method": "nearest", "gamma": 7.0, "tau": None,
                                  "appearance_matching": False})  # fmt: skip
    try:
        assert running.viewer is not None and _get(running.url) is not None
        # the initial settings (ns-nerfuser-view --blend-method/--gamma/--tau/--appearance-matching) reach the model
        # and its panel
        model = running.pipeline.model
        assert (model.blend_method, model.gamma, model.tau, model.appearance_matching) == ("nearest", 7.0, None, False)
        controls = model.viewer_scene.controls
        assert (controls["blend_method"].value, controls["gamma"].value, controls["tau"].value) == ("nearest", 7.0, 0.0)
        assert controls["appearance_matching"].value is False
        datamanager = running.pipeline.datamanager
        # no test images: no eval dataset, or (when a run's dataset is readable) its training cameras without images
        assert datamanager.eval_dataset is None or isinstance(datamanager.eval_dataset, PlaceholderImageDataset)
        with pytest.raises(RuntimeError, match="no test images"):
            len(datamanager.fixed_indices_eval_dataloader)  # ns-eval still gets the clear message
    finally:
        running.stop()
    assert port_closed(running.port)


def test_bad_input_is_one_line(tmp_path):
    spec = tmp_path / "fusion.json"
    spec.write_text(json.dumps({"runs": [str(tmp_path / "missing" / "config.yml")]}))
    proc = subprocess.run(
        [str(BIN / "ns-nerfuser-view"), str(spec)], capture_output=True, text=True, timeout=300, cwd=tmp_path
    )
    assert proc.returncode == 1
    lines = [line for line in proc.stderr.strip().splitlines() if line.startswith("ns-nerfuser-view:")]
    assert len(lines) == 1 and "missing/config.yml: no such file" in lines[0], proc.stderr[-2000:]
    assert "Traceback" not in proc.stderr
    with pytest.raises(ViewerSetupError, match="a nerfacto-cpu run, not a fused one; open it with ns-viewer"):
        load_fused_pipeline(RUNS[0])
    with pytest.raises(ViewerSetupError, match="nowhere.json: no such file or folder"):
        load_fused_pipeline(tmp_path / "nowhere.json")
    # blend options are checked before anything loads (the spec's runs do not even exist here)
    with pytest.raises(ViewerSetupError, match="gamma must be >= 0, got -1.0"):
        ViewCommand(path=spec, gamma=-1.0).main()
    with pytest.raises(ViewerSetupError, match="tau must be >= 1"):
        ViewCommand(path=spec, tau=0.5).main()


def test_an_impossible_bind_fails_at_once(fusion_spec, tmp_path):
    with pytest.raises(ViewerSetupError, match=r"--port 70000: not a TCP port"):
        check_bind("127.0.0.1", 70000)
    with pytest.raises(ViewerSetupError, match=r"--host 'no-such-host.invalid': cannot be resolved"):
        check_bind("no-such-host.invalid", None)
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        with pytest.raises(ViewerSetupError, match=r"cannot serve on 127.0.0.1:\d+ .*pick another --port"):
            check_bind("127.0.0.1", taken.getsockname()[1])
    # the command: one line and exit 1, not a viewer waiting forever on a dead server thread
    proc = subprocess.run([str(BIN / "ns-nerfuser-view"), str(fusion_spec), "--port", "70000", "--timeout", "60"],
                          capture_output=True, text=True, timeout=120, cwd=tmp_path)  # fmt: skip
    assert proc.returncode == 1, proc.stderr[-2000:]
    assert proc.stderr.strip().splitlines()[-1].startswith("ns-nerfuser-view: --port 70000: not a TCP port")

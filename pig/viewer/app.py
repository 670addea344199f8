"""The viewer's page: viser's web client with an orbiting camera, a timeline, an LOD switch, the capture's cameras
and, at a capture camera, the ground truth image beside the render.

Two drawing paths. `browser`: the level's splats go to the page as viser Gaussian splats (the LOD's anchors are
the prefix of the anchor list that the level holds), drawn there with their view-independent colour; the server
sends new splats only when the frame or the level changes. `server`: the server renders every connected
client's view with the project's renderer (gsplat on CUDA, the compositor on the CPU: exact, view-dependent
colour) through the driver's real-time path and streams JPEG frames; the page shows them as its background,
stretched over its canvas where they are smaller (`render_height`, the CPU's default).

Updates run on worker threads that always take the latest state, so dragging the slider faster than frames
are made skips frames instead of queueing them. What a page sends is not trusted: a control's value outside its
range is clamped or ignored, a canvas is rendered at most MAX_CANVAS_SIDE pixels on a side, an error making one
client's frame is reported and the next frame made, and only the viewer's own pages connect (pig.viewer.guard).
"""
from __future__ import annotations

import sys
import threading
import time
from pathlib import Path

import numpy as np
import torch

from pig.avatar.animation import Orbit, orbit_cameras
from pig.avatar.driver import AvatarDriver

from .guard import RequestGuard, guarded_server
from .splats import browser_splats, camera_pose
from .timeline import Timeline

ORBIT = "orbit"
PATHS = ("browser", "server")
# The server path's frame height on the CPU: the compositor's time grows with the pixels (16k splats: ~35 ms a frame
# at 240 x 180, ~70 ms at 320 x 240); at 180 lines a pose change reaches a page on a loaded 2-core machine in
# 170-240 ms (benchmarks/NOTES.md, "The viewer on the CPU"); the page stretches the frames over its canvas.
CPU_RENDER_HEIGHT = 180
# The largest side the server path renders, whatever canvas a page reports (a 1,000,000 x 180 one took 8.5 GB);
# a larger canvas gets a frame of its aspect, stretched over it.
MAX_CANVAS_SIDE = 4096


class _Latest:
    """A worker thread that runs `work()` whenever poked, at most once per batch of pokes. An error in `work` is
    said on stderr (each kind once) and the thread waits for the next poke: it never ends the thread."""

    def __init__(self, work, name: str):
        self._work, self._poked, self._stopped = work, threading.Event(), False
        self._name, self._reported = name, set()
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    def poke(self) -> None:
        self._poked.set()

    def stop(self) -> None:
        self._stopped = True
        self._poked.set()
        self._thread.join(timeout=10)

    def _run(self) -> None:
        while True:
            self._poked.wait()
            self._poked.clear()
            if self._stopped:
                return
            try:
                self._work()
            except Exception as err:  # one bad frame (a client's camera, say) must not stop the others
                why = f"{type(err).__name__}: {err}"
                if why not in self._reported:
                    self._reported.add(why)
                    print(f"view: {self._name}: {why}; the viewer goes on", file=sys.stderr, flush=True)


class Viewer:
    """A viser server showing the avatar of `driver` along `timeline`; `capture` (a pig.data.capture.Capture or
    None) adds its cameras and ground truth images. `path` is "browser" or "server" (see the module's doc);
    `jpeg_quality` is the server path's frame encoding; `render_height` (None: the page's canvas size) caps the
    height of the frames it renders, the page stretching them over its canvas. Pages of `allow_origins` (origins
    such as "https://name.example") may connect besides the viewer's own (pig.viewer.guard). Call `close()` to
    stop it."""

    def __init__(self, driver: AvatarDriver, timeline: Timeline, capture=None, path: str = "browser",
                 host: str = "127.0.0.1", port: int = 8080, jpeg_quality: int = 85, render_height: int | None = None,
                 allow_origins: tuple[str, ...] = ()):
        if path not in PATHS:
            raise ValueError(f"viewer path must be one of {PATHS}, got {path!r}")
        model = driver.model
        self.driver, self.timeline, self.capture, self.path = driver, timeline, capture, path
        self.jpeg_quality = jpeg_quality
        if render_height is not None and render_height < 1:
            raise ValueError(f"viewer render_height must be a positive number of pixels, got {render_height}")
        self.render_height = render_height
        self._lock = threading.Lock()  # one frame at a time through the driver (its CUDA graph outputs are shared)
        self.server = guarded_server(RequestGuard(host, tuple(allow_origins)), host=host, port=port, verbose=False)
        self.server.gui.configure_theme(control_layout="floating", dark_mode=True, show_share_button=False)
        self.server.scene.set_up_direction(tuple(float(v) for v in timeline.up))
        self.frames_sent = 0  # frames the server path has handed to viser, over all clients
        self.updates = 0  # splat updates the browser path has handed to viser

        centre, extent = timeline.bounds()
        viewmats, K = orbit_cameras(1, 1.0, centre, timeline.up, extent, Orbit())
        eye = -viewmats[0][:3, :3].T @ viewmats[0][:3, 3]
        self._home = camera_pose(viewmats[0], K, Orbit.height_px, float(np.linalg.norm(eye - centre)))
        home = self.server.initial_camera  # where a new page's camera starts, and its "reset view"
        home.position, home.look_at, home.fov = self._home["position"], self._home["look_at"], self._home["fov"]
        home.up = self._home["up_direction"]

        gui = self.server.gui
        self._levels = [f"{level}: {n} splats" for level, n in enumerate(model.level_sizes)]
        self._level, self._frame = len(self._levels) - 1, 0  # the last good values of the LOD and frame controls
        self.lod = gui.add_dropdown("LOD", self._levels, initial_value=self._levels[-1])
        self.frame = gui.add_slider(f"frame ({timeline.source})", min=0, max=max(timeline.length - 1, 1), step=1,
                                    initial_value=0, disabled=timeline.length < 2)
        self.play = gui.add_checkbox("play", initial_value=False)
        cameras, seen = [ORBIT], set()
        if capture is not None:  # each camera once, named with its first split (training first)
            for split in ("train", *sorted(s for s in capture.split if s != "train")):
                cameras += [f"{c} ({split})" for c in capture.split[split]["cameras"] if c not in seen]
                seen.update(capture.split[split]["cameras"])
        self._cameras = cameras
        self.camera = gui.add_dropdown("camera", cameras, initial_value=ORBIT, disabled=capture is None)
        self.truth = gui.add_image(np.zeros((8, 8, 3), np.uint8), label="ground truth", visible=False)

        self.splats = None
        self._renderers: dict[int, _Latest] = {}
        if path == "browser":
            self._scene = _Latest(self._update_splats, "viewer-splats")
        else:
            self._scene = None
            self.server.on_client_disconnect(self._drop_client)
        self.server.on_client_connect(self._new_client)
        self.lod.on_update(lambda _: self._changed())
        self.frame.on_update(lambda _: self._changed())
        self.camera.on_update(self._jump)
        self._player = threading.Thread(target=self._play, name="viewer-player", daemon=True)
        self._closed = False
        self._player.start()
        self._changed()

    # ---- state ----

    @property
    def level(self) -> int:
        """The LOD control's level; a value outside its options (only a crafted message sends one) is ignored."""
        if self.lod.value in self._levels:
            self._level = self._levels.index(self.lod.value)
        return self._level

    @property
    def frame_index(self) -> int:
        """The frame slider's timeline entry, clamped to the timeline; a value that is no integer is ignored."""
        try:
            index = int(self.frame.value)
        except (TypeError, ValueError, OverflowError):
            return self._frame
        self._frame = min(max(index, 0), self.timeline.length - 1)
        return self._frame

    @property
    def camera_choice(self) -> str:
        """The camera control's choice; a value outside its options reads as the orbit."""
        return self.camera.value if self.camera.value in self._cameras else ORBIT

    @property
    def url(self) -> str:
        return f"http://{self.server.get_host()}:{self.server.get_port()}"

    def set_camera(self, client, pose: dict) -> None:
        """Move a client's camera to a `camera_pose` dict."""
        with client.atomic():
            client.camera.position = pose["position"]
            client.camera.look_at = pose["look_at"]
            client.camera.up_direction = pose["up_direction"]
            client.camera.fov = pose["fov"]

    def capture_camera_pose(self, name: str) -> dict:
        cam = self.capture.cameras[name]
        distance = float(np.linalg.norm(cam.center - self._home["look_at"]))
        return camera_pose(cam.viewmat(), cam.K, cam.height, distance)

    def _changed(self) -> None:
        if self._scene is not None:
            self._scene.poke()
        for renderer in list(self._renderers.values()):
            renderer.poke()
        self._show_truth()

    def _new_client(self, client) -> None:
        if self.path == "server":
            renderer = _Latest(lambda: self._render_client(client), f"viewer-client-{client.client_id}")
            self._renderers[client.client_id] = renderer
            client.camera.on_update(lambda _: renderer.poke())
            renderer.poke()

    def _drop_client(self, client) -> None:
        renderer = self._renderers.pop(client.client_id, None)
        if renderer is not None:
            renderer.stop()

    def _jump(self, event) -> None:
        choice = self.camera_choice
        if choice != ORBIT:
            pose = self.capture_camera_pose(choice.split(" (")[0])
            clients = [event.client] if event.client is not None else list(self.server.get_clients().values())
            for client in clients:
                self.set_camera(client, pose)
        self._show_truth()

    def _show_truth(self) -> None:
        """The ground truth image of the chosen capture camera at the shown training frame, where there is one."""
        choice = self.camera_choice
        timestep = self.timeline.timestep(self.frame_index)
        if self.capture is None or choice == ORBIT or timestep is None:
            self.truth.visible = False
            return
        name, frame = choice.split(" (")[0], self.driver.model.frame_ids[timestep]
        if not self.capture.has(name, frame):
            self.truth.visible = False
            return
        image = self.capture.image(name, frame, background=np.zeros(3))
        self.truth.image = np.round(image * 255).astype(np.uint8)
        self.truth.label = f"ground truth: {name}, frame {frame}"
        self.truth.visible = True

    def _play(self) -> None:
        """Advance the timeline at the motion's frame rate while `play` is ticked."""
        while not self._closed:
            start = time.perf_counter()
            if self.play.value and self.timeline.length > 1:
                self.frame.value = (self.frame_index + 1) % self.timeline.length
            time.sleep(max(0.0, 1.0 / self.timeline.fps - (time.perf_counter() - start)))

    # ---- the two drawing paths ----

    def _update_splats(self) -> None:
        level, index = self.level, self.frame_index
        with self._lock:
            centres, covariances, rgb, opacities = browser_splats(*self.timeline.gaussians(level, index))
        if self.splats is None:
            self.splats = self.server.scene.add_gaussian_splats("/avatar", centres, covariances, rgb, opacities)
        else:
            self.splats.set_gaussians(centres, covariances, rgb, opacities)
        self.updates += 1

    def _render_client(self, client) -> None:
        from pig.render.api import render_gaussians

        camera = client.camera
        try:
            width, height = int(camera.image_width), int(camera.image_height)
            wxyz, position, fov = np.asarray(camera.wxyz), np.asarray(camera.position), float(camera.fov)
        except AssertionError:  # the client has not reported its camera yet
            return
        if width < 1 or height < 1:
            return
        width, height = frame_size(width, height, self.render_height)
        viewmat, K = viser_view(wxyz, position, fov, width, height)
        device = self.driver.device
        with self._lock:
            means, quats, scales, opacities, sh = self.timeline.gaussians(self.level, self.frame_index)
            out = render_gaussians(means.float(), quats.float(), scales.float(), opacities.float(), sh.float(),
                                   torch.as_tensor(viewmat, dtype=torch.float32, device=device)[None],
                                   torch.as_tensor(K, dtype=torch.float32, device=device)[None], width, height,
                                   torch.zeros(3, device=device))
            rgb = (out.color[0].clamp(0, 1) * 255).round().to(torch.uint8).cpu().numpy()
        if client.client_id not in self._renderers:  # the page closed while the frame was made
            return
        client.scene.set_background_image(rgb, format="jpeg", jpeg_quality=self.jpeg_quality)
        self.frames_sent += 1

    def close(self) -> None:
        self._closed = True
        if self._scene is not None:
            self._scene.stop()
        for renderer in list(self._renderers.values()):
            renderer.stop()
        self.server.stop()


def frame_size(width: int, height: int, render_height: int | None = None) -> tuple[int, int]:
    """(width, height) the server path renders a page's `width` x `height` canvas at: the canvas's aspect and field
    of view, at most `render_height` lines (None: no such cap) and MAX_CANVAS_SIDE pixels on either side."""
    scale = min(1.0, MAX_CANVAS_SIDE / width, MAX_CANVAS_SIDE / height,
                render_height / height if render_height is not None else 1.0)
    if scale == 1.0:
        return width, height
    return max(1, round(width * scale)), max(1, round(height * scale))


def viser_view(wxyz: np.ndarray, position: np.ndarray, fov: float, width: int, height: int
               ) -> tuple[np.ndarray, np.ndarray]:
    """(world-to-camera (4, 4), K (3, 3)) of a viser camera: `wxyz` rotates camera axes (OpenCV: x right, y down,
    z forward) into the world, `position` is its centre, `fov` its vertical field of view (radians) of a
    `width` x `height` image with the principal point at the centre."""
    w, x, y, z = (float(v) for v in np.asarray(wxyz) / np.linalg.norm(wxyz))
    rotation = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                         [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                         [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])
    viewmat = np.eye(4)
    viewmat[:3, :3] = rotation.T
    viewmat[:3, 3] = -rotation.T @ np.asarray(position, dtype=np.float64)
    focal = 0.5 * height / np.tan(0.5 * fov)
    return viewmat, np.array([[focal, 0.0, width / 2], [0.0, focal, height / 2], [0.0, 0.0, 1.0]])


def open_viewer(checkpoint: Path, motion: Path | None = None, capture_dir: Path | None = None, host: str = "127.0.0.1",
                port: int = 8080, device: str = "auto", path: str | None = None, render_height: int | None = None,
                allow_origins: tuple[str, ...] = ()) -> Viewer:
    """Load the avatar of `checkpoint` on `device` and serve it; `path` defaults to "server" (on the CPU too: a
    browser without a GPU draws 16k splats several times slower than the CPU renders a small frame);
    `render_height` as `Viewer`'s, default CPU_RENDER_HEIGHT on the CPU; `allow_origins` as `Viewer`'s."""
    from pig.avatar.checkpoint import load_avatar
    from pig.config import resolve_device
    from pig.data.capture import Capture
    from pig.field.precondition import bake_preconditioning

    device = resolve_device(device, "--device")
    model = load_avatar(checkpoint, device)
    bake_preconditioning(model)  # the anchors' value once, not a solve per frame
    driver = AvatarDriver(model, frame_graph=True)
    timeline = Timeline(driver, motion)
    capture = Capture.load(capture_dir) if capture_dir is not None else None
    if path is None:
        path = "server"
    if render_height is None and device.type != "cuda":
        render_height = CPU_RENDER_HEIGHT
    if device.type == "cuda":
        timeline.gaussians(model.num_levels - 1, 0)  # compile and capture the frame before a page waits for it
    return Viewer(driver, timeline, capture, path, host, port, render_height=render_height,
                  allow_origins=allow_origins)

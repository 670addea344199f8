"""The browser viewer (pig.viewer): splat and camera conversions against float64 references, the timeline against the
driver, and the page itself in a real headless Chromium: the avatar's pixels where the camera sees it, and the
timeline moving them.

The browser test needs Debian's chromium (`.ci/run` installs it where it runs as root) and the `viewer` extra; it
skips and says why where either is missing.
"""
from __future__ import annotations

import importlib.util
import math
import socket
import time

import numpy as np
import pytest
import torch

from pig.body.rotation import axis_angle_to_matrix
from pig.viewer.splats import SH_C0, browser_splats, camera_pose

VISER = importlib.util.find_spec("viser") is not None


def _browser_skip_reason() -> str | None:
    from pig.viewer.browser import find_chromium

    if not VISER:
        return "viser is not installed (pip install -e '.[viewer]')"
    if find_chromium() is None:
        return "Chromium is not installed (Debian: apt-get install chromium; .ci/run installs it as root)"
    return None


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def test_browser_splats_match_float64_reference(rng):
    n = 50
    means = torch.as_tensor(rng.normal(size=(n, 3)))
    quats = torch.as_tensor(rng.normal(size=(n, 4)))  # not unit: the conversion normalises
    scales = torch.as_tensor(rng.uniform(0.01, 0.2, size=(n, 3)))
    opacities = torch.as_tensor(rng.uniform(size=n))
    sh = torch.as_tensor(rng.normal(size=(n, 4, 3)))
    centres, covariances, rgb, alpha = browser_splats(means, quats, scales, opacities, sh)
    # Reference: rotation from the axis-angle of the unit quaternion (Rodrigues), covariance R S^2 R^T.
    q = quats.numpy() / np.linalg.norm(quats.numpy(), axis=1, keepdims=True)
    angle = 2 * np.arctan2(np.linalg.norm(q[:, 1:], axis=1), q[:, 0])
    axis = q[:, 1:] / np.linalg.norm(q[:, 1:], axis=1, keepdims=True)
    rotation = axis_angle_to_matrix(torch.as_tensor(axis * angle[:, None])).numpy()
    expected = np.einsum("nij,nj,nkj->nik", rotation, scales.numpy() ** 2, rotation)
    np.testing.assert_allclose(covariances, expected, rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(centres, means.numpy(), rtol=1e-6)
    np.testing.assert_allclose(rgb, np.clip(sh.numpy()[:, 0] / (2 * math.sqrt(math.pi)) + 0.5, 0, 1), atol=1e-6)
    np.testing.assert_allclose(alpha[:, 0], opacities.numpy(), rtol=1e-6)
    assert SH_C0 == pytest.approx(1 / (2 * math.sqrt(math.pi)), rel=1e-15)
    assert all(a.dtype == np.float32 for a in (centres, covariances, rgb, alpha))


@pytest.mark.skipif(not VISER, reason="viser is not installed (pip install -e '.[viewer]')")
def test_viser_view_inverts_camera_pose(rng):
    """A capture camera taken to viser's camera state and back (as the server path reads it) projects points
    where the capture camera does, for a viewport of the capture's size."""
    import viser.transforms as tf

    from pig.viewer.app import viser_view

    rotation = axis_angle_to_matrix(torch.as_tensor(rng.normal(size=3))).numpy()
    viewmat = np.eye(4)
    viewmat[:3, :3], viewmat[:3, 3] = rotation, rng.normal(size=3)
    width, height = 160, 120
    K = np.array([[150.0, 0, width / 2], [0, 150.0, height / 2], [0, 0, 1]])
    pose = camera_pose(viewmat, K, height, distance=2.5)
    centre = -rotation.T @ viewmat[:3, 3]
    np.testing.assert_allclose(pose["position"], centre, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(pose["look_at"] - centre), 2.5, rtol=1e-12)
    # viser's own orientation of a camera at `position` looking at `look_at` with `up_direction` up.
    forward = (pose["look_at"] - pose["position"]) / 2.5
    right = np.cross(forward, pose["up_direction"])
    right /= np.linalg.norm(right)
    wxyz = tf.SO3.from_matrix(np.stack([right, np.cross(forward, right), forward], axis=1)).wxyz
    view, K_view = viser_view(wxyz, pose["position"], pose["fov"], width, height)
    points = centre + rotation.T @ np.array([0.3, -0.2, 3.0]) + rng.normal(scale=0.1, size=(20, 3))
    def project(vm, k):
        cam = points @ vm[:3, :3].T + vm[:3, 3]
        return (cam @ k.T)[:, :2] / cam[:, 2:]
    np.testing.assert_allclose(project(view, K_view), project(viewmat, K), atol=1e-8)


@pytest.fixture(scope="module")
def trained_looking_avatar(tmp_path_factory):
    """A small avatar on the stand-in body (3 timesteps, 3 levels) with a refiner and decoders far from zero."""
    from pig.body.params import SmplxParams
    from pig.body.standin import write_standin
    from pig.field.precondition import bake_preconditioning
    from avatar_fixture import small_avatar

    path = tmp_path_factory.mktemp("standin") / "body_model.npz"
    write_standin(path)
    rng = np.random.default_rng(0)
    params = SmplxParams(rng.normal(scale=0.2, size=(3, 55, 3)), np.zeros(10), np.zeros((3, 10)),
                         rng.normal(scale=0.1, size=(3, 3)))
    model = small_avatar(path.read_bytes(), params, num_anchors=400, levels=3, sh_degree=1, hidden_layers=2,
                         hidden_width=16)
    with torch.no_grad():
        for layer in [*model.decoder.modules(), *model.refiner.modules()]:
            if isinstance(layer, torch.nn.Linear):
                layer.weight.normal_(std=0.5)
    bake_preconditioning(model)
    return model.eval()


def test_training_timeline_shows_each_timestep_as_the_model_renders_it(trained_looking_avatar):
    """Timeline entry t without a motion: the model's own splats of training timestep t (its refined pose and
    translation, its decoded outputs), at each level; from the stacked decoder outputs when they fit the
    driver's budget, from its per-timestep path when not."""
    from pig.avatar.driver import AvatarDriver
    from pig.viewer.timeline import Timeline

    model = trained_looking_avatar
    stacked = Timeline(AvatarDriver(model, frame_graph=True))
    per_timestep = Timeline(AvatarDriver(model, frame_graph=True, decoded_budget_bytes=1000))
    assert stacked.length == model.num_timesteps and stacked.motion is None
    for lod, t in ((0, 0), (1, 2), (2, 1)):
        assert stacked.timestep(t) == t
        reference = model.gaussians(t, lod)
        for timeline in (stacked, per_timestep):
            for ours, theirs in zip(timeline.gaussians(lod, t), reference):
                torch.testing.assert_close(ours, theirs)
    with pytest.raises(ValueError, match="timeline index must lie in 0..2"):
        stacked.gaussians(0, 3)


def test_motion_timeline_is_the_aligned_motion(trained_looking_avatar):
    """With a motion, the timeline holds its frames as `animate` places them (align_motion onto the capture's
    up axis, ground and centre) and shows each through the driver's pose path."""
    from pig.avatar.driver import AvatarDriver
    from pig.body.motion import DEMO_MOTION, align_motion, capture_frame, read_motion
    from pig.viewer.timeline import Timeline

    model = trained_looking_avatar
    driver = AvatarDriver(model, frame_graph=True)
    timeline = Timeline(driver, DEMO_MOTION)
    motion = read_motion(DEMO_MOTION, hands_mean=model.body_model.hands_mean.numpy())
    up, ground, centre = capture_frame(model)
    aligned = align_motion(motion, model.body_model, driver.refined()[0], up, ground, centre)
    assert timeline.length == motion.num_frames and timeline.fps == motion.fps and timeline.timestep(0) is None
    plain = AvatarDriver(model)
    for index in (0, motion.num_frames - 1):
        np.testing.assert_allclose(timeline.motion.full_pose[index], aligned.full_pose[index], rtol=0, atol=0)
        for ours, theirs in zip(timeline.gaussians(2, index), plain.gaussians(2, aligned.full_pose[index],
                                                                              aligned.transl[index])):
            torch.testing.assert_close(ours, theirs)


@pytest.mark.skipif(not VISER, reason="viser is not installed (pip install -e '.[viewer]')")
@pytest.mark.parametrize("render_height", [None, 72])
def test_server_path_streams_the_renderers_image_of_the_clients_camera(trained_looking_avatar, render_height):
    """The server path on the CPU: a scripted client reports a camera (as a browser does) and receives a JPEG that
    equals the project's renderer at that camera, whose world-to-camera matrix is built here by look-at. With a
    `render_height` below the canvas's, the frame has that height, the canvas's aspect and its field of view."""
    import cv2

    from pig.avatar.animation import look_at
    from pig.avatar.driver import AvatarDriver
    from pig.render.api import render_gaussians
    from pig.viewer.app import Viewer
    from pig.viewer.client import ViserClient, camera_message
    from pig.viewer.timeline import Timeline

    model = trained_looking_avatar
    driver = AvatarDriver(model, frame_graph=True)
    timeline = Timeline(driver)
    viewer = Viewer(driver, timeline, path="server", port=free_port(), jpeg_quality=100, render_height=render_height)
    width, height, fov = 96, 72, math.radians(40.0)
    canvas_width, canvas_height = (width, height) if render_height is None else (2 * width, 2 * height)
    centre, extent = timeline.bounds()
    up = np.asarray(timeline.up, dtype=np.float64)
    side = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 1.0, 0.0])
    eye = centre + 1.6 * extent * side / np.linalg.norm(side)

    def reference(eye) -> np.ndarray:
        focal = 0.5 * height / math.tan(fov / 2)
        K = torch.tensor([[focal, 0, width / 2], [0, focal, height / 2], [0, 0, 1]], dtype=torch.float32)
        viewmat = torch.as_tensor(look_at(eye, centre, up), dtype=torch.float32)
        splats = [t.float() for t in timeline.gaussians(viewer.level, 0)]
        out = render_gaussians(*splats, viewmat[None], K[None], width, height, torch.zeros(3))
        return out.color[0].clamp(0, 1).numpy()

    try:
        client = ViserClient(f"ws://127.0.0.1:{viewer.server.get_port()}")
        try:
            client.send(camera_message(eye, centre, up, fov, canvas_width, canvas_height))
            expected, frames = reference(eye), []
            # A frame is made per camera report (and one may predate ours): the last one is of our camera.
            while (data := client.next_frame(20.0 if not frames else 2.0)) is not None:
                frames.append(cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)[..., ::-1] / 255.0)
        finally:
            client.close()
    finally:
        viewer.close()
    assert frames, "no frame reached the client"
    frame = frames[-1]
    assert frame.shape == (height, width, 3)
    assert (expected.max(-1) > 0.1).mean() > 0.05, "the avatar barely shows: the comparison would say little"
    assert np.abs(frame - expected).mean() < 2 / 255, f"mean difference {np.abs(frame - expected).mean() * 255:.1f} / 255"
    moved = reference(eye + 0.05 * extent * up)
    assert np.abs(frame - moved).mean() > 4 * np.abs(frame - expected).mean(), "the check cannot tell cameras apart"


def _status(port: int, host: str, origin: str | None = None, websocket: bool = True) -> int:
    """The HTTP status the viewer on `port` answers a request with these Host and Origin headers: 101 when it opens
    the websocket, 403 when it refuses; without `websocket`, the page's GET (200 when served)."""
    import base64
    import os

    import viser

    lines = ["GET / HTTP/1.1", f"Host: {host}"]
    if websocket:
        key = base64.b64encode(os.urandom(16)).decode()
        lines += ["Upgrade: websocket", "Connection: Upgrade", f"Sec-WebSocket-Key: {key}", "Sec-WebSocket-Version: 13",
                  f"Sec-WebSocket-Protocol: viser-v{viser.__version__}"]
    if origin is not None:
        lines.append(f"Origin: {origin}")
    with socket.create_connection(("127.0.0.1", port), timeout=30) as connection:
        connection.sendall(("\r\n".join(lines) + "\r\n\r\n").encode())
        head = b""
        while b"\r\n" not in head:
            chunk = connection.recv(256)
            if not chunk:
                break
            head += chunk
    return int(head.split(b" ")[1])


@pytest.mark.skipif(not VISER, reason="viser is not installed (pip install -e '.[viewer]')")
def test_the_viewer_opens_its_websocket_to_its_own_pages_only(trained_looking_avatar):
    """Another site's page (cross-site websocket hijacking), a name of another site turned into 127.0.0.1 (DNS
    rebinding) and another port are refused; the viewer's own page under a loopback name and scripts without an
    Origin are admitted, and `allow_origins` admits a tunnel's origin, whatever Host the tunnel passes on."""
    from pig.avatar.driver import AvatarDriver
    from pig.viewer.app import Viewer
    from pig.viewer.timeline import Timeline

    timeline = Timeline(AvatarDriver(trained_looking_avatar))
    viewer = Viewer(timeline.driver, timeline, path="browser", port=free_port())
    try:
        port = viewer.server.get_port()
        own = [(f"127.0.0.1:{port}", None), (f"127.0.0.1:{port}", f"http://127.0.0.1:{port}"),
               (f"localhost:{port}", f"http://localhost:{port}"), (f"[::1]:{port}", f"http://[::1]:{port}")]
        foreign = [(f"127.0.0.1:{port}", "http://evil.example"), (f"127.0.0.1:{port}", f"http://localhost:{port}"),
                   (f"127.0.0.1:{port}", "null"), (f"evil.example:{port}", f"http://evil.example:{port}"),
                   (f"evil.example:{port}", None), (f"127.0.0.1:{port + 1}", f"http://127.0.0.1:{port + 1}"),
                   ("127.0.0.1", None), (f"127.0.0.1:{port}", "https://tunnel.example")]
        assert [_status(port, host, origin) for host, origin in own] == [101] * len(own)
        assert [_status(port, host, origin) for host, origin in foreign] == [403] * len(foreign)
        assert _status(port, f"127.0.0.1:{port}", websocket=False) == 200
        assert _status(port, f"evil.example:{port}", websocket=False) == 403  # the page itself, by a rebound name
    finally:
        viewer.close()
    viewer = Viewer(timeline.driver, timeline, path="browser", port=free_port(),
                    allow_origins=("https://tunnel.example",))
    try:
        port = viewer.server.get_port()
        assert _status(port, "tunnel.example", "https://tunnel.example") == 101
        assert _status(port, f"127.0.0.1:{port}", "https://tunnel.example") == 101  # a tunnel that rewrites Host
        assert _status(port, "tunnel.example", websocket=False) == 200
        assert _status(port, f"127.0.0.1:{port}", "http://evil.example") == 403
    finally:
        viewer.close()


@pytest.mark.skipif(not VISER, reason="viser is not installed (pip install -e '.[viewer]')")
def test_view_stage_checks_allow_origin(tmp_path, capsys):
    from pig.stages.view import main

    with pytest.raises(SystemExit):
        main(["--checkpoint", str(tmp_path / "avatar.pt"), "--allow-origin", "evil.example"])
    assert "is not an origin: expected http(s)://HOST[:PORT]" in capsys.readouterr().err


def _side_view(timeline):
    """(eye, centre, up) of a camera beside the body, 1.6 body sizes away."""
    centre, extent = timeline.bounds()
    up = np.asarray(timeline.up, dtype=np.float64)
    side = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 1.0, 0.0])
    return centre + 1.6 * extent * side / np.linalg.norm(side), centre, up


def _received(client, first_wait_s: float = 20.0) -> np.ndarray | None:
    """The last frame (RGB in [0, 1]) `client` receives before 2 s pass without one; None if none comes."""
    import cv2

    frame = None
    while (data := client.next_frame(first_wait_s if frame is None else 2.0)) is not None:
        frame = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)[..., ::-1] / 255.0
    return frame


@pytest.mark.skipif(not VISER, reason="viser is not installed (pip install -e '.[viewer]')")
def test_crafted_control_values_stop_no_client(trained_looking_avatar):
    """A page sends an LOD outside the dropdown's options and a frame far past the timeline's end: the viewer keeps
    the level and shows the last frame, and this client and a new one get frames of it, equal to the renderer's."""
    from pig.avatar.animation import look_at
    from pig.avatar.driver import AvatarDriver
    from pig.render.api import render_gaussians
    from pig.viewer.app import Viewer
    from pig.viewer.client import ViserClient, camera_message, gui_message
    from pig.viewer.timeline import Timeline

    model = trained_looking_avatar
    timeline = Timeline(AvatarDriver(model, frame_graph=True))
    viewer = Viewer(timeline.driver, timeline, path="server", port=free_port(), jpeg_quality=100)
    width, height, fov = 64, 48, math.radians(40.0)
    eye, centre, up = _side_view(timeline)
    focal = 0.5 * height / math.tan(fov / 2)
    K = torch.tensor([[focal, 0, width / 2], [0, focal, height / 2], [0, 0, 1]], dtype=torch.float32)
    viewmat = torch.as_tensor(look_at(eye, centre, up), dtype=torch.float32)
    last = timeline.length - 1
    expected = render_gaussians(*[t.float() for t in timeline.gaussians(model.num_levels - 1, last)], viewmat[None],
                                K[None], width, height, torch.zeros(3)).color[0].clamp(0, 1).numpy()
    url = f"ws://127.0.0.1:{viewer.server.get_port()}"
    try:
        first = ViserClient(url)
        try:
            first.send(camera_message(eye, centre, up, fov, width, height))
            assert _received(first) is not None
            first.send(gui_message(viewer.lod, "99: crafted"))
            first.send(gui_message(viewer.frame, 10**9))
            first.send(camera_message(eye, centre, up, fov, width, height + 2))  # a new camera report: a new frame
            assert _received(first, 10.0) is not None, "the client that sent the values gets no frame"
            second = ViserClient(url)
            try:
                second.send(camera_message(eye, centre, up, fov, width, height))
                frame = _received(second)
            finally:
                second.close()
        finally:
            first.close()
        assert viewer.level == model.num_levels - 1 and viewer.frame_index == last
    finally:
        viewer.close()
    assert frame is not None, "a client connecting afterwards gets no frame"
    difference = np.abs(frame - expected).mean()
    assert difference < 2 / 255, f"mean difference {difference * 255:.1f} / 255 from the last frame at the finest level"


def test_an_error_making_one_frame_stops_no_later_frame():
    """The viewer's worker thread (one per client on the server path): a frame that raises is reported, and the
    next poke makes the next frame."""
    import threading

    from pig.viewer.app import _Latest

    made, done = [], threading.Event()

    def work():
        made.append(len(made))
        if len(made) == 1:
            raise RuntimeError("a client's camera made this frame fail")
        done.set()

    worker = _Latest(work, "viewer-client-test")
    try:
        worker.poke()
        while not made:  # the first frame started: a poke from now on asks for another
            time.sleep(0.01)
        worker.poke()
        assert done.wait(10), "the worker thread ended with the failed frame"
    finally:
        worker.stop()
    assert made == [0, 1]


@pytest.mark.skipif(not VISER, reason="viser is not installed (pip install -e '.[viewer]')")
def test_a_canvas_is_rendered_at_most_max_side_pixels_on_a_side(trained_looking_avatar):
    """A page reporting a canvas twice the bound's width gets a frame of the bound's width and the canvas's aspect;
    the 1,000,000 x 180 canvas that took 8.5 GB is rendered at 4096 x 1."""
    from pig.avatar.driver import AvatarDriver
    from pig.viewer.app import Viewer
    from pig.viewer.client import ViserClient, camera_message
    from pig.viewer.timeline import Timeline

    bound = 4096
    timeline = Timeline(AvatarDriver(trained_looking_avatar, frame_graph=True))
    viewer = Viewer(timeline.driver, timeline, path="server", port=free_port())
    eye, centre, up = _side_view(timeline)
    try:
        client = ViserClient(f"ws://127.0.0.1:{viewer.server.get_port()}")
        try:
            client.send(camera_message(eye, centre, up, math.radians(40.0), 2 * bound, 8))
            frame = _received(client)
        finally:
            client.close()
    finally:
        viewer.close()
    assert frame is not None and frame.shape == (4, bound, 3)
    from pig.viewer.app import MAX_CANVAS_SIDE, frame_size

    assert MAX_CANVAS_SIDE == bound  # as docs/viewer.md states
    assert frame_size(1_000_000, 180) == (4096, 1) and frame_size(180, 10**9) == (1, 4096)
    assert frame_size(5000, 5000, render_height=180) == (180, 180) and frame_size(640, 480) == (640, 480)


def _footprint(means: np.ndarray, scales: np.ndarray, viewmat: np.ndarray, focal: float, width: int, height: int,
               sigmas: float) -> np.ndarray:
    """Pixels within `sigmas` times each splat's largest standard deviation of its centre's projection through a
    centred pinhole of focal length `focal` (float64; a splat's footprint bound, sigmas=0: the centres' pixels)."""
    import cv2

    cam = means.astype(np.float64) @ viewmat[:3, :3].T + viewmat[:3, 3]
    front = cam[:, 2] > 0
    cam, scales = cam[front], scales[front]
    u = focal * cam[:, 0] / cam[:, 2] + width / 2
    v = focal * cam[:, 1] / cam[:, 2] + height / 2
    radius = sigmas * scales.max(axis=1) * focal / cam[:, 2]
    mask = np.zeros((height, width), np.uint8)
    for x, y, r in zip(u, v, radius):
        if -r <= x < width + r and -r <= y < height + r:
            cv2.circle(mask, (int(round(x)), int(round(y))), int(math.ceil(r)), 1, thickness=-1)
    return mask.astype(bool)


def iou(a: np.ndarray, b: np.ndarray) -> float:
    return float((a & b).sum() / max(1, (a | b).sum()))


@pytest.mark.slow
@pytest.mark.skipif(_browser_skip_reason() is not None, reason=str(_browser_skip_reason()))
def test_viewer_in_headless_chromium(tiny_fit, tmp_path):
    """The view stage's viewer on a fitted avatar, seen by Chromium from a capture camera: the avatar's pixels (the
    canvas with the splats shown against it with them hidden) lie where the capture camera projects the splat
    centres, cover most of that projection, and a click on the timeline's slider moves them to the next
    training pose's projection."""
    from pig.data.capture import Capture
    from pig.viewer.app import open_viewer
    from pig.viewer.browser import HeadlessChromium

    capture_dir, checkpoint = tiny_fit
    width, height = 640, 480
    viewer = open_viewer(checkpoint, None, capture_dir, port=free_port(), device="cpu", path="browser")
    try:
        capture = Capture.load(capture_dir)
        name = capture.split["train"]["cameras"][0]
        cam = capture.cameras[name]
        with HeadlessChromium(width, height) as browser:
            browser.goto(viewer.url + "/?fixedDpr=1")
            browser.wait_for("document.querySelector('[role=slider]') !== null && document.querySelector('canvas') !== null")
            end = time.monotonic() + 30
            while viewer.splats is None or not viewer.server.get_clients():
                assert time.monotonic() < end, "the viewer sent no splats to the page"
                time.sleep(0.05)
            viewer.camera.value = f"{name} (train)"  # the dropdown's jump, for every client
            assert viewer.truth.visible, "no ground truth image shown at a capture camera"
            np.testing.assert_array_equal(viewer.truth.image, np.round(capture.image(name, viewer.driver.model.frame_ids[0],
                                                                                      np.zeros(3)) * 255).astype(np.uint8))
            client = next(iter(viewer.server.get_clients().values()))
            end = time.monotonic() + 30
            while not np.allclose(client.camera.position, cam.center, atol=1e-4):  # the page reports its camera
                assert time.monotonic() < end, "the page's camera did not move to the capture camera"
                time.sleep(0.05)

            def bare() -> np.ndarray:
                """Pixels that no control covers: outside every box of a positioned element that holds no canvas."""
                boxes = browser.evaluate(
                    "[...document.querySelectorAll('*')].filter(e => ['absolute', 'fixed'].includes(getComputedStyle(e)"
                    ".position) && getComputedStyle(e).pointerEvents !== 'none' && e.tagName !== 'CANVAS' && "
                    "!e.querySelector('canvas')).map(e => "
                    "e.getBoundingClientRect()).filter(r => r.width * r.height > 0).map(r => [r.left, r.top, r.right, r.bottom])")
                free = np.ones((height, width), bool)
                for left, top, right, bottom in boxes:
                    free[max(0, math.floor(top)) : math.ceil(bottom), max(0, math.floor(left)) : math.ceil(right)] = False
                return free

            def avatar_pixels() -> tuple[np.ndarray, np.ndarray]:
                """(pixels where the page's screenshot changes when the splats are shown, the screenshot)."""
                viewer.splats.visible = False
                time.sleep(1.0)
                empty = browser.screenshot().astype(int)
                viewer.splats.visible = True
                time.sleep(1.0)
                shown = browser.screenshot()
                assert shown.shape == (height, width, 3), shown.shape
                return np.abs(shown - empty).max(-1) > 12, shown

            focal = height * cam.K[1][1] / cam.height  # the capture's vertical field of view over the page's height

            def expected(timestep: int, sigmas: float) -> np.ndarray:
                means, _, scales = (t.cpu().numpy() for t in viewer.timeline.gaussians(viewer.level, timestep)[:3])
                return _footprint(means, scales, cam.viewmat(), focal, width, height, sigmas)

            # The notification that WebGL runs in software (SwiftShader) would cover the avatar: taken off the page.
            browser.evaluate("document.head.insertAdjacentHTML('beforeend', "
                             "'<style>.mantine-Notifications-root { display: none !important; }</style>')")
            free = bare()
            assert free.mean() > 0.4, f"controls cover {1 - free.mean():.0%} of the page"
            first, page = avatar_pixels()
            import cv2

            cv2.imwrite(str(tmp_path / "page.png"), page[..., ::-1])  # kept with the test's files for a look
            first &= free
            assert first.sum() > 200, f"the avatar covers only {first.sum()} pixels"
            assert (first & expected(0, sigmas=3)).sum() / first.sum() > 0.95, "avatar pixels where the camera sees no splat"
            # Against the splats' 2-sigma footprints: IoU 0.91 here; a field of view 10 % too wide gives 0.79.
            assert iou(first, expected(0, sigmas=2) & free) > 0.85, "the avatar is not where the camera sees it"

            # A click on the slider's track where frame 1 lies (the track spans frames 0 to its max).
            left, top, right, bottom = browser.evaluate(
                "(r => [r.left, r.top, r.right, r.bottom])(document.querySelector('.mantine-Slider-track')"
                ".getBoundingClientRect())")
            browser.click(left + (right - left) / viewer.frame.max, (top + bottom) / 2)
            end = time.monotonic() + 30
            while int(viewer.frame.value) != 1:
                assert time.monotonic() < end, f"the click on the slider did not reach the viewer ({viewer.frame.value})"
                time.sleep(0.05)
            second = avatar_pixels()[0] & free
            moved = second & ~first
            assert moved.sum() > 50, f"moving the timeline uncovered only {moved.sum()} new avatar pixels"
            assert (moved & expected(1, sigmas=3)).sum() / moved.sum() > 0.95, "new pixels outside the next pose"
            now, before = iou(second, expected(1, sigmas=2) & free), iou(second, expected(0, sigmas=2) & free)
            assert now > 0.85 and now > before, f"the page shows frame 1 at IoU {now:.2f}, frame 0 at {before:.2f}"
    finally:
        viewer.close()


@pytest.mark.skipif(not VISER, reason="viser is not installed (pip install -e '.[viewer]')")
def test_view_stage_names_a_missing_checkpoint(tmp_path, capsys):
    from pig._cli import run_cli
    from pig.stages.view import main

    missing = tmp_path / "avatar.pt"
    assert run_cli(main, ["--checkpoint", str(missing), "--port", str(free_port())]) == 1
    error = capsys.readouterr().err
    assert error.startswith("view: error: ") and str(missing) in error and "not found" in error


@pytest.mark.skipif(_browser_skip_reason() is not None, reason=str(_browser_skip_reason()))
@pytest.mark.parametrize("gl, name", [("swiftshader", "SwiftShader"), ("llvmpipe", "llvmpipe")])
def test_headless_chromium_draws_webgl_on_the_chosen_renderer(gl, name):
    from pathlib import Path

    from pig.viewer.browser import HeadlessChromium

    if gl == "llvmpipe" and not list(Path("/usr/lib").glob("*/dri/swrast_dri.so")):
        pytest.skip("Mesa's llvmpipe is not installed (Debian: apt-get install libgl1-mesa-dri)")
    with HeadlessChromium(160, 120, gl=gl) as browser:
        assert name in browser.webgl_renderer()
    with pytest.raises(ValueError, match="gl: expected one of"):
        HeadlessChromium(gl="opengl")

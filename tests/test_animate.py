"""Animate stage: turntable and motion videos on a tiny fitted avatar, framing and orientation, camera choice, errors."""
import json

import cv2
import numpy as np
import pytest

from pig.avatar.animation import Orbit, animate, look_at
from pig.body.motion import DEMO_MOTION
from pig.render.api import RasterizerConfig
from pig.stages import animate as animate_stage

CPU = RasterizerConfig(backend="cpu")


@pytest.fixture(scope="module")
def fitted(tiny_fit):
    return tiny_fit


def _video_frames(path):
    video = cv2.VideoCapture(str(path))
    frames = []
    while True:
        ok, frame = video.read()
        if not ok:
            return frames
        frames.append(frame)


def _alpha(path):
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert image.shape[2] == 4, "PNG frames carry alpha"
    return image[..., 3].astype(np.float32) / 255


def test_look_at_is_a_rigid_opencv_camera():
    eye, target, up = np.array([3.0, 1.0, 0.5]), np.array([0.0, 1.0, 0.0]), np.array([0.0, 1.0, 0.0])
    viewmat = look_at(eye, target, up)
    rotation = viewmat[:3, :3]
    np.testing.assert_allclose(rotation @ rotation.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(rotation) == pytest.approx(1.0)
    np.testing.assert_allclose(viewmat[:3, :3] @ eye + viewmat[:3, 3], 0, atol=1e-12)  # the eye is the camera centre
    in_camera = viewmat[:3, :3] @ target + viewmat[:3, 3]
    assert in_camera[2] > 0 and abs(in_camera[0]) < 1e-12 and abs(in_camera[1]) < 1e-12  # straight ahead
    above = viewmat[:3, :3] @ (target + up) + viewmat[:3, 3]
    assert above[1] < 0  # world up is image up (OpenCV's y points down)
    with pytest.raises(ValueError, match="parallel to the up axis"):
        look_at(np.array([0.0, 3.0, 0.0]), target, up)


@pytest.mark.slow
def test_turntable_video_keeps_the_avatar_in_view(fitted, tmp_path):
    _, checkpoint = fitted
    out = tmp_path / "turntable"
    video = animate(checkpoint, out, orbit=Orbit(period_s=1.0, width=48, height_px=40), fps=6, png=True, rasterizer=CPU)
    assert video == out / "animation.webm"
    frames = _video_frames(video)
    assert len(frames) == 6 and frames[0].shape == (40, 48, 3)
    record = json.loads((out / "animation.json").read_text())
    assert record["frames"] == 6 and record["fps"] == 6 and record["camera"] == "orbit" and record["lod"] == 1
    pngs = sorted((out / "frames").glob("*.png"))
    assert len(pngs) == 6
    for png in pngs:
        alpha = _alpha(png)
        rows, cols = np.nonzero(alpha > 0.5)
        assert len(rows) > 20, f"{png.name}: the avatar is out of view"
        # Upright and framed: taller than wide, inside the image with a margin.
        assert np.ptp(rows) > np.ptp(cols) and rows.min() > 0 and rows.max() < 39


@pytest.mark.slow
def test_demo_motion_is_brought_upright_into_the_capture_frame(fitted, tmp_path):
    _, checkpoint = fitted
    out = tmp_path / "demo"
    animate(checkpoint, out, DEMO_MOTION, frames="0:40:10", orbit=Orbit(width=40, height_px=48), png=True, rasterizer=CPU)
    record = json.loads((out / "animation.json").read_text())
    assert record["frames"] == 4 and record["fps"] == pytest.approx(30 / 10)
    for png in sorted((out / "frames").glob("*.png")):
        rows, cols = np.nonzero(_alpha(png) > 0.5)
        assert len(rows) > 20 and np.ptp(rows) > np.ptp(cols), f"{png.name}: the z-up clip is not upright in view"


@pytest.mark.slow
def test_capture_camera_and_bad_input(fitted, tmp_path, capsys):
    from pig._cli import run_cli
    from pig.stages.animate import main

    capture, checkpoint = fitted
    cameras = json.loads((capture / "cameras.json").read_text())
    camera = sorted(cameras)[0]
    out = tmp_path / "camera"
    animate(checkpoint, out, camera=camera, capture_dir=capture, static_seconds=0.2, fps=10, lod=0, rasterizer=CPU)
    frames = _video_frames(out / "animation.webm")
    assert len(frames) == 2 and frames[0].shape[:2] == (cameras[camera]["height"], cameras[camera]["width"])

    capsys.readouterr()  # the render's progress bar
    base = ["--checkpoint", str(checkpoint), "--preset", "test", "--device", "cpu"]
    cases = [
        (["--output", str(tmp_path / "a"), "--camera", "nope", "--capture", str(capture)], "no camera 'nope'; cameras: "),
        (["--output", str(tmp_path / "b"), "--camera", camera], "--camera needs --capture DIR"),
        (["--output", str(tmp_path / "c"), "--lod", "7"], "--lod 7: the avatar has levels 0..1"),
        (["--output", str(tmp_path / "d"), "--motion", str(tmp_path / "missing.npz")], "missing.npz: motion file not found"),
        (["--output", str(tmp_path / "e"), "--motion", str(DEMO_MOTION), "--frames", "5:2"], "--frames '5:2' selects no frame"),
    ]
    for argv, message in cases:
        assert run_cli(main, base + argv) == 1
        err = capsys.readouterr().err.strip()
        assert err.startswith("animate: error: ") and message in err and "\n" not in err, err
        assert not (tmp_path / argv[1]).exists()


def test_video_page_embeds_the_video_whole(tmp_path):
    import base64
    import re

    from pig.render.video_page import is_video_page, video_page

    video = tmp_path / "clip.webm"
    video.write_bytes(bytes(range(256)) * 7)
    page = video_page(video, "a <clip>")
    embedded = re.search(r'<video [^>]*src="data:video/webm;base64,([A-Za-z0-9+/=]+)"', page).group(1)
    assert base64.b64decode(embedded) == video.read_bytes() and "a &lt;clip&gt;" in page
    (tmp_path / "page.html").write_text(page)
    assert is_video_page(tmp_path / "page.html") and not is_video_page(video)
    with pytest.raises(ValueError, match=r"clip\.gif: expected a video file ending in \.webm or \.mp4"):
        video_page(tmp_path / "clip.gif", "x")


def test_page_option_leaves_a_file_it_did_not_write(tmp_path, capsys):
    other = tmp_path / "notes.html"
    other.write_text("<p>mine</p>")
    with pytest.raises(SystemExit) as exit_info:
        animate_stage.main(["--checkpoint", str(tmp_path / "avatar.pt"), "--output", str(tmp_path / "out"),
                            "--page", str(other), "--device", "cpu"])
    assert exit_info.value.code == 2 and other.read_text() == "<p>mine</p>"
    assert f"--page: {other} exists and is not a page this stage wrote; pass --overwrite to replace it" in capsys.readouterr().err


@pytest.mark.parametrize("where", ["inside the output", "the checkpoint"])
def test_page_option_refuses_the_checkpoint_and_the_output_folder(tmp_path, where):
    from pig._outputs import OutputError

    checkpoint = tmp_path / "avatar.pt"
    checkpoint.write_bytes(b"weights")
    page = tmp_path / "out" / "page.html" if where == "inside the output" else checkpoint
    message = "lies inside the input" if where == "inside the output" else "is the input"
    with pytest.raises(OutputError, match=rf"{page}: the output {message}"):
        animate_stage.main(["--checkpoint", str(checkpoint), "--output", str(tmp_path / "out"), "--page", str(page),
                            "--device", "cpu", "--overwrite"])
    assert checkpoint.read_bytes() == b"weights"

"""Frames per second that reach a client of the viewer's server path (frames rendered on the server, JPEG over
viser's websocket), counted by a scripted websocket client.

The client speaks viser's protocol: it reports a camera of --size pixels (ViewerCameraMessage) moving along an
orbit at --camera-hz, as a browser does while the view is dragged, and counts the BackgroundImageMessages it
receives (each a frame) over --seconds; the timeline plays the demo motion meanwhile (the driver's real-time
path: a CUDA graph per LOD on CUDA), so frames change pose and camera. Also prints the server's parts, each
synchronised: pose -> splats (Timeline.gaussians), raster (pig.render.api), copy to the host, and JPEG encoding
(OpenCV, which viser uses). The avatar is
built unfitted at the preset's sizes (only the timings mean anything) and saves the last frame received.

    python benchmarks/viewer_stream.py --device cuda --json out.json --frame frame.jpg      # 100k splats, 1280 x 720
    python benchmarks/viewer_stream.py --device cpu --preset test --anchors 1500 --size 160 120 --seconds 3
"""
from __future__ import annotations

import argparse
import json
import math
import socket
import statistics
import sys
import threading
import time
from pathlib import Path

import numpy as np
import torch

from pig.avatar.driver import AvatarDriver
from pig.body.motion import DEMO_MOTION
from pig.field.precondition import bake_preconditioning
from pig.viewer.app import Viewer, viser_view
from pig.viewer.client import ViserClient, camera_message
from pig.viewer.timeline import Timeline

sys.path.insert(0, str(Path(__file__).parent))
from render_fps import build_unfitted  # noqa: E402


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


class OrbitClient(ViserClient):
    """A scripted viser client that reports an orbiting camera at `hz` and counts the frames it receives."""

    def __init__(self, url: str, width: int, height: int, centre: np.ndarray, up: np.ndarray, radius: float, hz: float):
        super().__init__(url)
        self.width, self.height, self.centre, self.up, self.radius, self.hz = width, height, centre, up, radius, hz
        self.arrivals: list[float] = []
        self.frame_bytes: list[int] = []
        self.last_frame: bytes | None = None
        self.stopped = False

    def camera_message(self, angle: float) -> bytes:
        up = self.up / np.linalg.norm(self.up)
        side = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 1.0, 0.0])
        side /= np.linalg.norm(side)
        eye = self.centre + self.radius * (math.cos(angle) * side + math.sin(angle) * np.cross(up, side))
        return camera_message(eye, self.centre, up, math.radians(40.0), self.width, self.height)

    def send_cameras(self) -> None:
        step = 0
        while not self.stopped:
            self.send(self.camera_message(2 * math.pi * step / (8 * self.hz)))  # one turn in 8 s
            step += 1
            time.sleep(1.0 / self.hz)

    def receive(self, seconds: float) -> None:
        end = time.perf_counter() + seconds
        while time.perf_counter() < end:
            frame = self.next_frame(end - time.perf_counter())
            if frame is None:
                break
            self.arrivals.append(time.perf_counter())
            self.frame_bytes.append(len(frame))
            self.last_frame = frame


def parts_ms(viewer: Viewer, client: OrbitClient, repeats: int) -> dict[str, float]:
    """Median ms of the server's parts of one frame, each synchronised, on new poses of the timeline."""
    import cv2

    from pig.render.api import render_gaussians

    device = viewer.driver.device
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
    message = client.camera_message(0.3)
    import msgspec

    camera = msgspec.msgpack.decode(message)
    viewmat, K = viser_view(np.asarray(camera["wxyz"]), np.asarray(camera["position"]), camera["fov"], client.width,
                            client.height)
    viewmat_t = torch.as_tensor(viewmat, dtype=torch.float32, device=device)[None]
    K_t = torch.as_tensor(K, dtype=torch.float32, device=device)[None]
    times = {"pose -> splats": [], "raster": [], "to host": [], "jpeg": []}
    for i in range(repeats):
        sync()
        start = time.perf_counter()
        splats = [t.float().clone() for t in viewer.timeline.gaussians(viewer.level, i % viewer.timeline.length)]
        sync()
        posed = time.perf_counter()
        out = render_gaussians(*splats, viewmat_t, K_t, client.width, client.height, torch.zeros(3, device=device))
        sync()
        rastered = time.perf_counter()
        rgb = (out.color[0].clamp(0, 1) * 255).round().to(torch.uint8).cpu().numpy()
        hosted = time.perf_counter()
        cv2.imencode(".jpg", rgb[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, viewer.jpeg_quality])  # as viser encodes it
        done = time.perf_counter()
        for name, (a, b) in zip(times, ((start, posed), (posed, rastered), (rastered, hosted), (hosted, done))):
            times[name].append(1e3 * (b - a))
    return {name: statistics.median(values) for name, values in times.items()}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--device", default="cuda")
    parser.add_argument("--preset", default="paper", help="compute preset of the unfitted avatar's sizes")
    parser.add_argument("--anchors", type=int, default=100_000, help="splats of the finest level")
    parser.add_argument("--timesteps", type=int, default=30, help="training timesteps of the unfitted avatar")
    parser.add_argument("--size", type=int, nargs=2, default=(1280, 720), metavar=("WIDTH", "HEIGHT"))
    parser.add_argument("--seconds", type=float, default=10.0, help="how long the client counts frames")
    parser.add_argument("--camera-hz", type=float, default=120.0, help="camera reports a second from the client")
    parser.add_argument("--repeats", type=int, default=30, help="frames for the server's parts")
    parser.add_argument("--json", type=Path, help="write the numbers here")
    parser.add_argument("--frame", type=Path, help="save the last frame received (JPEG) here")
    args = parser.parse_args(argv)
    device = torch.device(args.device)
    torch.manual_seed(0)
    model = build_unfitted(args.preset, args.anchors, args.timesteps).to(device)
    bake_preconditioning(model)
    driver = AvatarDriver(model.eval(), frame_graph=True)
    timeline = Timeline(driver, DEMO_MOTION)
    started = time.perf_counter()
    timeline.gaussians(model.num_levels - 1, 0)  # compile and capture the shown (finest) level's frame first
    warmup_s = time.perf_counter() - started
    viewer = Viewer(driver, timeline, path="server", port=free_port())
    try:
        centre, extent = timeline.bounds()
        radius = 0.5 * extent / 0.75 / math.tan(math.radians(20.0))
        client = OrbitClient(f"ws://127.0.0.1:{viewer.server.get_port()}", *args.size, centre, timeline.up, radius,
                             args.camera_hz)
        sender = threading.Thread(target=client.send_cameras, daemon=True)
        sender.start()
        client.receive(3.0)  # the first frames: the connection's set-up and the JPEG encoder's first use
        client.arrivals.clear()
        client.frame_bytes.clear()
        sent_before = viewer.frames_sent
        viewer.play.value = True
        started = time.perf_counter()
        client.receive(args.seconds)
        elapsed = time.perf_counter() - started
        viewer.play.value = False
        client.stopped = True
        sender.join(timeout=5)
        frames = len(client.arrivals)
        gaps = np.diff(client.arrivals) * 1e3 if frames > 1 else np.array([float("nan")])
        result = {
            "device": torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu",
            "splats": model.level_sizes[viewer.level], "width": args.size[0], "height": args.size[1],
            "seconds": elapsed, "frames_received": frames, "fps_received": frames / elapsed,
            "frames_rendered": viewer.frames_sent - sent_before,
            "gap_ms_median": float(np.median(gaps)), "gap_ms_p95": float(np.percentile(gaps, 95)),
            "jpeg_kib_median": float(np.median(client.frame_bytes)) / 1024 if frames else float("nan"),
            "camera_hz": args.camera_hz, "warmup_s": warmup_s,
            "server_parts_ms": parts_ms(viewer, client, args.repeats),
        }
        if args.frame is not None and client.last_frame is not None:
            args.frame.parent.mkdir(parents=True, exist_ok=True)
            args.frame.write_bytes(client.last_frame)
        client.close()
    finally:
        viewer.close()
    print(f"{result['device']}: {result['splats']} splats, {args.size[0]} x {args.size[1]}, camera at "
          f"{args.camera_hz:.0f} Hz, timeline playing; warm-up (compile + capture of the level) {warmup_s:.1f} s")
    print("| frames received | fps | frame gap median / p95 ms | JPEG KiB | " +
          " | ".join(f"{k} ms" for k in result["server_parts_ms"]) + " |")
    print("|---" * (4 + len(result["server_parts_ms"])) + "|")
    print(f"| {frames} | **{result['fps_received']:.1f}** | {result['gap_ms_median']:.1f} / {result['gap_ms_p95']:.1f} | "
          f"{result['jpeg_kib_median']:.0f} | " + " | ".join(f"{v:.2f}" for v in result["server_parts_ms"].values()) + " |")
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())

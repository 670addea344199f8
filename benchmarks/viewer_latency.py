"""Pose-change latency of the viewer on the CPU, in a real headless Chromium (WebGL on SwiftShader).

Each sample clicks the timeline's slider at the next frame and times, in the page's own clock, from the slider's
pointerdown event to the first animation frame whose canvas pixels differ from those before it (a 160 x 120
downsample, >= 20 pixels changed by > 30 levels summed over RGB), split at the arrival in the page of the splats or
the frame that the change sent (viser's websocket worker posting them to the page). Beside it, the server's share, timed apart: the
frame's splats from the driver (`Timeline.gaussians`), then either their conversion for viser (`browser_splats`,
`--draw browser`: the page draws the splats) or the CPU renderer's frame at the rendered size and its JPEG
(`--draw server`: the page shows the server's frames, `--render-height` lines stretched over its canvas); and the
CPU time that the browser's processes and the server's threads spend per pose change: on a machine shared with
other jobs the wall time waits for the cores, the CPU time does not.

    python benchmarks/viewer_latency.py                    # an unfitted cpu-demo avatar, 16k splats, the server's frames
    python benchmarks/viewer_latency.py --draw browser     # the splats drawn in the page
    python benchmarks/viewer_latency.py --checkpoint avatar.pt --capture capture/ --screenshot docs/viewer_cpu.png

--screenshot saves the page (jumped to the capture's first training camera when --capture is given).
"""
from __future__ import annotations

import argparse
import socket
import statistics
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import torch

from pig.avatar.driver import AvatarDriver
from pig.field.precondition import bake_preconditioning
from pig.viewer.app import CPU_RENDER_HEIGHT, Viewer
from pig.viewer.browser import GL_FLAGS, HeadlessChromium
from pig.viewer.splats import browser_splats
from pig.viewer.timeline import Timeline

sys.path.insert(0, str(Path(__file__).parent))
from render_fps import build_unfitted  # noqa: E402

# In the page: on the slider's pointerdown, keep a downsample of the 3D canvas and poll each animation frame until
# the canvas differs; `__pig.latency` is then the milliseconds between the two.
WATCH = """
window.__pig = (() => {
  const canvas = [...document.querySelectorAll('canvas')].reduce((a, b) => b.width * b.height > a.width * a.height ? b : a);
  const small = document.createElement('canvas');
  small.width = 160; small.height = 120;
  const ctx = small.getContext('2d', {willReadFrequently: true});
  const grab = () => { ctx.clearRect(0, 0, 160, 120); ctx.drawImage(canvas, 0, 0, 160, 120);
                       return ctx.getImageData(0, 0, 160, 120).data; };
  const state = {latency: null, arrival: null};
  document.querySelector('.mantine-Slider-root').addEventListener('pointerdown', () => {
    const start = performance.now();
    const before = grab();
    state.latency = null;
    const poll = () => {
      const now = grab();
      let changed = 0;
      for (let i = 0; i < now.length; i += 4)
        if (Math.abs(now[i] - before[i]) + Math.abs(now[i + 1] - before[i + 1]) + Math.abs(now[i + 2] - before[i + 2]) > 30) changed++;
      if (changed >= 20) {
        const now = performance.now(), big = window.__pigArrivals.filter(([t]) => t >= start);
        state.arrival = big.length ? big[big.length - 1][0] - start : null;
        state.latency = now - start;
      } else requestAnimationFrame(poll);
    };
    requestAnimationFrame(poll);
  }, {capture: true});
  return state;
})()
"""

# Before the page's scripts: the arrival time of every batch of messages that holds splats or a frame (viser's
# websocket runs in a worker, which posts the decoded batches to the page), so that the latency splits into the part
# until they arrived and the page's part after it.
ARRIVALS = """
window.__pigArrivals = [];
const PlainWorker = window.Worker;
window.Worker = class extends PlainWorker {
  constructor(...args) {
    super(...args);
    this.addEventListener('message', e => {
      const messages = (e.data && e.data.messages) || [];
      const drawn = m => /Background|Gaussian/.test(m.type)
                         || (m.type === 'SceneNodeUpdateMessage' && 'buffer' in m.updates);
      if (messages.some(drawn)) window.__pigArrivals.push([performance.now(), 1]);
    });
  }
};
"""


def cpu_seconds(root: int) -> float:
    """User + system CPU time (s) of process `root` and its descendants (Linux /proc), for the browser's work."""
    import os

    ticks, parents = os.sysconf("SC_CLK_TCK"), {}
    stats = {}
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                fields = open(f"/proc/{entry}/stat").read().rsplit(")", 1)[1].split()
            except OSError:
                continue
            parents[int(entry)] = int(fields[1])
            stats[int(entry)] = (int(fields[11]) + int(fields[12])) / ticks
    tree, grown = {root}, True
    while grown:
        more = {pid for pid, parent in parents.items() if parent in tree} - tree
        tree |= more
        grown = bool(more)
    return sum(stats.get(pid, 0.0) for pid in tree)


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def server_frame(viewer: Viewer, gaussians, width: int, height: int):
    """The server path's frame of `gaussians` (uint8 RGB) at the page's initial camera, as `Viewer` renders it."""
    from pig.render.api import render_gaussians
    from pig.viewer.app import viser_view
    import viser.transforms as tf

    home = viewer._home  # the page's camera until it moves
    forward = (home["look_at"] - home["position"]) / np.linalg.norm(home["look_at"] - home["position"])
    right = np.cross(forward, home["up_direction"])
    right /= np.linalg.norm(right)
    wxyz = tf.SO3.from_matrix(np.stack([right, np.cross(forward, right), forward], axis=1)).wxyz
    viewmat, K = viser_view(wxyz, home["position"], home["fov"], width, height)
    with torch.no_grad():
        out = render_gaussians(*(t.float() for t in gaussians), torch.as_tensor(viewmat, dtype=torch.float32)[None],
                               torch.as_tensor(K, dtype=torch.float32)[None], width, height, torch.zeros(3))
    return (out.color[0].clamp(0, 1) * 255).round().to(torch.uint8).numpy()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--checkpoint", type=Path, help="avatar.pt (default: an unfitted cpu-demo avatar)")
    parser.add_argument("--capture", type=Path, help="the checkpoint's preprocessed capture (cameras, ground truth)")
    parser.add_argument("--anchors", type=int, default=16000, help="splats of the unfitted avatar's finest level")
    parser.add_argument("--timesteps", type=int, default=24, help="training timesteps of the unfitted avatar")
    parser.add_argument("--samples", type=int, default=10, help="pose changes to time")
    parser.add_argument("--size", type=int, nargs=2, default=(800, 600), metavar=("WIDTH", "HEIGHT"), help="page size")
    parser.add_argument("--threads", type=int, default=2, help="torch CPU threads of the server")
    parser.add_argument("--draw", choices=["browser", "server"], default="server",
                        help="where splats are drawn (default: server, as the view stage on the CPU)")
    parser.add_argument("--render-height", type=int, default=CPU_RENDER_HEIGHT,
                        help=f"--draw server: height of the rendered frames (default: {CPU_RENDER_HEIGHT}, the view "
                             "stage's on the CPU)")
    parser.add_argument("--gl", choices=sorted(GL_FLAGS), default="swiftshader",
                        help="the page's WebGL renderer: Chromium's SwiftShader or Mesa's llvmpipe")
    parser.add_argument("--screenshot", type=Path, help="save the page as this PNG")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    if args.checkpoint is not None:
        from pig.viewer.app import open_viewer

        viewer = open_viewer(args.checkpoint, None, args.capture, port=free_port(), device="cpu", path=args.draw,
                             render_height=args.render_height)
    else:
        torch.manual_seed(0)
        model = build_unfitted("cpu-demo", args.anchors, args.timesteps)
        bake_preconditioning(model)
        driver = AvatarDriver(model.eval(), frame_graph=True)
        viewer = Viewer(driver, Timeline(driver), path=args.draw, port=free_port(), render_height=args.render_height)
    timeline, level = viewer.timeline, viewer.level
    splats = viewer.driver.model.level_sizes[level]
    try:
        server_ms, convert_ms, encode_ms = [], [], []
        height = min(args.size[1], args.render_height or args.size[1])
        width = round(args.size[0] * height / args.size[1])
        for index in range(min(args.samples, timeline.length)):
            start = time.perf_counter()
            gaussians = timeline.gaussians(level, index)
            middle = time.perf_counter()
            if args.draw == "browser":
                browser_splats(*gaussians)
            else:
                rgb = server_frame(viewer, gaussians, width, height)
            convert_ms.append(1e3 * (time.perf_counter() - middle))
            server_ms.append(1e3 * (middle - start))
            if args.draw == "server":
                middle = time.perf_counter()
                cv2.imencode(".jpg", rgb[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, viewer.jpeg_quality])
                encode_ms.append(1e3 * (time.perf_counter() - middle))
        latencies, arrivals, drawing = [], [], []
        with HeadlessChromium(*args.size, gl=args.gl) as browser:
            renderer = browser.webgl_renderer()
            browser.call("Page.enable")
            browser.call("Page.addScriptToEvaluateOnNewDocument", source=ARRIVALS)
            browser.goto(viewer.url + "/?fixedDpr=1")
            browser.wait_for("document.querySelector('.mantine-Slider-track') !== null")
            end = time.monotonic() + 60
            while max(viewer.updates, viewer.frames_sent) < 1 or not viewer.server.get_clients():
                if time.monotonic() > end:
                    raise TimeoutError("the viewer sent nothing to draw to the page")
                time.sleep(0.05)
            time.sleep(2.0)  # the first splats drawn
            assert browser.evaluate("Array.isArray(window.__pigArrivals) && window.__pigArrivals.length > 0"), \
                "no splats or frame seen arriving at the page"
            browser.evaluate(WATCH)
            left, top, right, bottom = browser.evaluate(
                "(r => [r.left, r.top, r.right, r.bottom])(document.querySelector('.mantine-Slider-track')"
                ".getBoundingClientRect())")
            steps = viewer.frame.max
            browser_cpu, server_cpu = cpu_seconds(browser.pid), time.process_time()
            for k in range(args.samples):
                target = (k + 1) % (steps + 1)
                browser.click(left + (right - left) * target / steps, (top + bottom) / 2)
                latencies.append(browser.wait_for("window.__pig.latency", timeout_s=60, every_s=0.02))
                arrival = browser.evaluate("window.__pig.arrival")
                if arrival is not None:
                    arrivals.append(arrival)
                    drawing.append(latencies[-1] - arrival)
                time.sleep(0.3)
            browser_cpu = (cpu_seconds(browser.pid) - browser_cpu) / args.samples * 1e3
            server_cpu = (time.process_time() - server_cpu) / args.samples * 1e3
            if args.screenshot is not None:
                # The notice that WebGL runs in software (SwiftShader) is headless Chromium's, not a user's.
                browser.evaluate("document.head.insertAdjacentHTML('beforeend', "
                                 "'<style>.mantine-Notifications-root { display: none !important; }</style>')")
                if args.capture is not None:
                    name = viewer.capture.split["train"]["cameras"][0]
                    viewer.camera.value = f"{name} (train)"
                    time.sleep(2.0)
                args.screenshot.parent.mkdir(parents=True, exist_ok=True)
                cv2.imwrite(str(args.screenshot), browser.screenshot()[..., ::-1])
    finally:
        viewer.close()
    load = open("/proc/loadavg").read().split()[0] if Path("/proc/loadavg").exists() else "?"
    drawn = "splats drawn in the browser" if args.draw == "browser" else f"frames of {width} x {height} from the server"
    print(f"splats {splats} (LOD {level}), page {args.size[0]} x {args.size[1]}, {drawn}, {args.threads} threads, "
          f"load average {load}, {len(latencies)} pose changes\nWebGL: {renderer}")
    print("| part | median ms | min | max |\n|---|---|---|---|")
    parts = [("slider event -> changed pixels (page)", latencies),
             ("slider event -> splats or frame arrived (page)", arrivals),
             ("arrival -> changed pixels (page)", drawing), ("driver frame (server)", server_ms)]
    if args.draw == "browser":
        parts.append(("conversion for viser (server)", convert_ms))
    else:
        parts += [("CPU renderer's frame (server)", convert_ms), ("JPEG (server)", encode_ms)]
    for name, values in parts:
        if not values:
            continue
        print(f"| {name} | {statistics.median(values):.0f} | {min(values):.0f} | {max(values):.0f} |")
    print(f"CPU time per pose change (all threads, 0.3 s idle after each included): browser {browser_cpu:.0f} ms, "
          f"server {server_cpu:.0f} ms")
    return 0


if __name__ == "__main__":
    sys.exit(main())

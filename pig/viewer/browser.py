"""A headless Chromium driven over the Chrome DevTools protocol: load a page, run script, press keys, take
screenshots. What the viewer's browser test and its latency benchmark use; nothing here is downloaded.

Chromium runs with a fresh profile, no sandbox (it runs as root in CI) and WebGL in software: SwiftShader,
Chromium's own CPU renderer (`--disable-gpu`: no GPU driver is used), or Mesa's llvmpipe through ANGLE's EGL backend
where Debian's `libgl1-mesa-dri` is installed (what Firefox and Chromium told to ignore their GPU blocklist use on a
Linux machine without a GPU; it draws viser's splats about twice as fast, benchmarks/NOTES.md).
"""
from __future__ import annotations

import base64
import json
import os
import shutil
import signal
import subprocess
import tempfile
import time
import urllib.request
from pathlib import Path

import cv2
import numpy as np

EXECUTABLES = ("chromium", "chromium-browser", "google-chrome")
FLAGS = ("--headless", "--no-sandbox", "--disable-quic", "--no-first-run", "--disable-background-networking",
         "--disable-component-update", "--disable-sync", "--hide-scrollbars", "--mute-audio")
# WebGL's software renderer -> its flags.
GL_FLAGS = {"swiftshader": ("--disable-gpu", "--use-angle=swiftshader", "--enable-unsafe-swiftshader"),
            "llvmpipe": ("--use-gl=angle", "--use-angle=gl-egl", "--ignore-gpu-blocklist")}


def find_chromium() -> str | None:
    """Path of an installed Chromium (or Chrome), or None."""
    for name in EXECUTABLES:
        found = shutil.which(name)
        if found:
            return found
    return None


def _decode_png(data: str) -> np.ndarray:
    image = cv2.imdecode(np.frombuffer(base64.b64decode(data), np.uint8), cv2.IMREAD_COLOR)
    return image[..., ::-1].copy()


class HeadlessChromium:
    """One headless browser with one page of `width` x `height` CSS pixels (device scale 1), WebGL on `gl` (a key of
    GL_FLAGS). Use as a context manager, or call `close()`."""

    def __init__(self, width: int = 800, height: int = 600, executable: str | None = None, timeout_s: float = 30.0,
                 gl: str = "swiftshader"):
        from websockets.sync.client import connect

        if gl not in GL_FLAGS:
            raise ValueError(f"gl: expected one of {', '.join(GL_FLAGS)}, found {gl!r}")
        executable = executable or find_chromium()
        if executable is None:
            raise OSError(f"no Chromium found (looked for {', '.join(EXECUTABLES)}; Debian: apt-get install chromium)")
        self._profile = tempfile.TemporaryDirectory(prefix="pig-chromium-")
        profile = Path(self._profile.name)
        self._log = open(profile / "chromium.log", "wb")
        self._process = subprocess.Popen([executable, *FLAGS, *GL_FLAGS[gl], f"--user-data-dir={profile}",
                                          "--remote-debugging-port=0", f"--window-size={width},{height}", "about:blank"],
                                         stdin=subprocess.DEVNULL, stdout=self._log, stderr=subprocess.STDOUT,
                                         start_new_session=True)  # its helpers in a group of their own: see close
        self._next_id = 0
        try:
            port = self._devtools_port(profile / "DevToolsActivePort", timeout_s)
            with urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=timeout_s) as reply:
                pages = [t for t in json.load(reply) if t.get("type") == "page"]
            self._socket = connect(pages[0]["webSocketDebuggerUrl"], max_size=None, open_timeout=timeout_s)
            self.call("Emulation.setDeviceMetricsOverride", width=width, height=height, deviceScaleFactor=1, mobile=False)
        except BaseException:
            self.close()
            raise

    def _devtools_port(self, port_file: Path, timeout_s: float) -> int:
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            if self._process.poll() is not None:
                raise OSError(f"Chromium exited with status {self._process.returncode} at start "
                              f"({(Path(self._profile.name) / 'chromium.log').read_text(errors='replace')[-500:]})")
            if port_file.exists() and port_file.read_text().count("\n") >= 1:
                return int(port_file.read_text().split("\n")[0])
            time.sleep(0.05)
        raise TimeoutError(f"Chromium did not open its DevTools port within {timeout_s} s")

    @property
    def pid(self) -> int:
        """Process id of the browser (its renderer and GPU processes are its children)."""
        return self._process.pid

    def call(self, method: str, **params) -> dict:
        """Send one DevTools command and return its result (events that arrive meanwhile are dropped)."""
        self._next_id += 1
        self._socket.send(json.dumps({"id": self._next_id, "method": method, "params": params}))
        while True:
            message = json.loads(self._socket.recv())
            if message.get("id") == self._next_id:
                if "error" in message:
                    raise RuntimeError(f"DevTools {method}: {message['error']}")
                return message.get("result", {})

    def goto(self, url: str) -> None:
        self.call("Page.navigate", url=url)

    def evaluate(self, expression: str):
        """The value of a JavaScript expression in the page (awaited when it is a promise)."""
        result = self.call("Runtime.evaluate", expression=expression, returnByValue=True, awaitPromise=True)
        if "exceptionDetails" in result:
            raise RuntimeError(f"page script failed: {result['exceptionDetails'].get('text')} ({expression[:80]})")
        return result["result"].get("value")

    def evaluate_in_frame(self, expression: str, index: int = 0):
        """The value of a JavaScript expression in the page's `index`-th child frame (an iframe, also one of
        another origin such as a data: URL, which the page's own script may not read)."""
        frames = self.call("Page.getFrameTree")["frameTree"].get("childFrames", [])
        if index >= len(frames):
            raise RuntimeError(f"page has {len(frames)} child frames, not {index + 1}")
        context = self.call("Page.createIsolatedWorld", frameId=frames[index]["frame"]["id"])["executionContextId"]
        result = self.call("Runtime.evaluate", expression=expression, contextId=context, returnByValue=True,
                           awaitPromise=True)
        if "exceptionDetails" in result:
            raise RuntimeError(f"frame script failed: {result['exceptionDetails'].get('text')} ({expression[:80]})")
        return result["result"].get("value")

    def wait_for(self, expression: str, timeout_s: float = 30.0, every_s: float = 0.05):
        """Poll a JavaScript expression until it is truthy; return its value."""
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            value = self.evaluate(expression)
            if value:
                return value
            time.sleep(every_s)
        raise TimeoutError(f"page: {expression[:80]} still false after {timeout_s} s")

    def click(self, x: float, y: float) -> None:
        """Press and release the left mouse button at page coordinates (x, y) (CSS pixels)."""
        self.call("Input.dispatchMouseEvent", type="mouseMoved", x=x, y=y)
        for kind in ("mousePressed", "mouseReleased"):
            self.call("Input.dispatchMouseEvent", type=kind, x=x, y=y, button="left", clickCount=1)

    def webgl_renderer(self) -> str:
        """The renderer a WebGL2 context of the page reports (which software renderer drew), or "no WebGL2"."""
        return self.evaluate(
            "(() => { const gl = document.createElement('canvas').getContext('webgl2'); if (!gl) return 'no WebGL2';"
            " const info = gl.getExtension('WEBGL_debug_renderer_info');"
            " return gl.getParameter(info ? info.UNMASKED_RENDERER_WEBGL : gl.RENDERER); })()")

    def screenshot(self) -> np.ndarray:
        """(H, W, 3) uint8 RGB of the page as shown."""
        return _decode_png(self.call("Page.captureScreenshot", format="png")["data"])

    def close(self) -> None:
        socket = getattr(self, "_socket", None)
        if socket is not None:
            socket.close()
        if self._process.poll() is None:
            self._process.terminate()
            try:
                self._process.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self._process.kill()
                self._process.wait()
        # Chromium's helpers (zygote, GPU, renderer) can outlive its main process by a moment and still write into
        # the profile, which the cleanup below would then fail to remove ("Directory not empty"): end the group.
        try:
            os.killpg(self._process.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        self._log.close()
        self._profile.cleanup()

    def __enter__(self) -> "HeadlessChromium":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

"""A scripted client of viser's websocket protocol: reports a camera as a browser does and receives the frames that
the viewer's server path streams. What the server path's test and its frame-rate benchmark use.

Server -> client messages are windows: 8 bytes msgpack size, 8 bytes compressed size, zstd msgpack of
{"messages": [...], "binaryBufferLengths": [...]}, then the binary buffers, each 8-byte aligned from the start.
Client -> server messages are plain msgpack of one message's fields and its "type".
"""
from __future__ import annotations

import numpy as np


def decode_window(raw: bytes) -> tuple[list[dict], list[memoryview]]:
    """The messages of one server -> client websocket message and its binary buffers."""
    import msgspec
    import zstandard

    size, compressed = int.from_bytes(raw[:8], "little"), int.from_bytes(raw[8:16], "little")
    payload = msgspec.msgpack.decode(zstandard.ZstdDecompressor().decompress(raw[16 : 16 + compressed], size))
    buffers, offset, view = [], 16 + compressed, memoryview(raw)
    for length in payload.get("binaryBufferLengths", ()):
        offset += (8 - offset % 8) % 8
        buffers.append(view[offset : offset + length])
        offset += length
    return payload["messages"], buffers


def camera_message(position, look_at, up, fov: float, width: int, height: int) -> bytes:
    """A ViewerCameraMessage of a camera at `position` looking at `look_at` with `up` up in the image, `fov`
    vertical (radians), reporting a `width` x `height` canvas."""
    import msgspec
    import viser.transforms as tf
    from viser._messages import ViewerCameraMessage

    position, look_at, up = (np.asarray(v, dtype=np.float64) for v in (position, look_at, up))
    forward = (look_at - position) / np.linalg.norm(look_at - position)
    right = np.cross(forward, up)
    right /= np.linalg.norm(right)
    wxyz = tf.SO3.from_matrix(np.stack([right, np.cross(forward, right), forward], axis=1)).wxyz  # OpenCV axes
    message = ViewerCameraMessage(wxyz=tuple(float(v) for v in wxyz), position=tuple(float(v) for v in position),
                                  fov=float(fov), near=0.01, far=100.0, image_height=int(height), image_width=int(width),
                                  look_at=tuple(float(v) for v in look_at), up_direction=tuple(float(v) for v in up))
    return msgspec.msgpack.encode(message.as_serializable_dict())


def gui_message(handle, value) -> bytes:
    """A GuiUpdateMessage setting the control `handle` (a viser GUI handle) to `value`, as a page sends it."""
    import msgspec
    from viser._messages import GuiUpdateMessage

    return msgspec.msgpack.encode(GuiUpdateMessage(handle._impl.uuid, {"value": value}).as_serializable_dict())


class ViserClient:
    """One websocket connection to a viser server at `url` (ws://host:port)."""

    def __init__(self, url: str, timeout_s: float = 30.0):
        import viser
        from websockets.sync.client import connect

        self.socket = connect(url, subprotocols=[f"viser-v{viser.__version__}"], max_size=None, compression=None,
                              open_timeout=timeout_s)

    def send(self, message: bytes) -> None:
        self.socket.send(message)

    def next_frame(self, timeout_s: float) -> bytes | None:
        """The encoded image (JPEG or PNG bytes) of the next background image received within `timeout_s`, or None."""
        import time

        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            try:
                raw = self.socket.recv(timeout=max(0.001, end - time.monotonic()))
            except TimeoutError:
                return None
            messages, buffers = decode_window(raw)
            for message in messages:
                if message.get("type") == "BackgroundImageMessage" and message.get("rgb_data") is not None:
                    data = message["rgb_data"]
                    if isinstance(data, dict):  # a placeholder for a binary buffer
                        data = buffers[data["__binary_index"]]
                    return bytes(data)
        return None

    def close(self) -> None:
        self.socket.close()

"""One camera's frames as a capture stores them: numbered image files in a folder, or one video file in its place.

The readers of the EasyMocap, ActorsHQ and AvatarReX layouts (`pig.data.easymocap`, `pig.data.actorshq`,
`pig.data.avatarrex`) share these. A video `X.mp4` (or .mkv, .avi, .mov) stands for the frame folder `X/`; its
i-th frame is frame i. Video frames are decoded in order, once, as the preprocess stage asks for them camera by
camera (a small window of decoded frames serves its threads' out-of-order requests); the declared frame size and
count are checked before any decoding.
Data preparation, no paper equation.
"""
from __future__ import annotations

import os
import re
import threading
from collections import OrderedDict
from pathlib import Path

import cv2
import numpy as np

from pig.data.images import read_image
from pig.data.raw import CaptureError
from pig.data.rectify import check_matte
from pig.inputs import require_regular_file
from pig.names import safe_name

VIDEO_SUFFIXES = (".mp4", ".mkv", ".avi", ".mov")
IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png")
# Decoded frames a video keeps: more than the preprocess stage's threads ask for at once.
VIDEO_WINDOW = 32


class FrameFiles:
    """Frame id -> file of one camera folder, from file names matching `pattern` (its group 1 is the frame id)."""

    def __init__(self, folder: Path, pattern: str, expected: str):
        self.path = folder
        self.files: dict[int, Path] = {}
        regex = re.compile(pattern)
        with os.scandir(folder) as entries:
            for entry in entries:
                stem, suffix = os.path.splitext(entry.name)
                match = regex.fullmatch(stem)
                if suffix.lower() not in IMAGE_SUFFIXES or not match:
                    continue
                frame = int(match.group(1))
                if frame in self.files:
                    raise CaptureError(f"{folder}: two files for frame {frame}: {self.files[frame].name} and "
                                       f"{entry.name} (expected {expected})")
                self.files[frame] = Path(entry.path)

    @property
    def frames(self):
        """The frame ids, as a view: membership is O(1) (the preprocess stage asks for every view)."""
        return self.files.keys()

    def read(self, frame: int, flags: int, max_pixels: int) -> np.ndarray:
        if frame not in self.files:
            raise CaptureError(f"{self.path}: no file for frame {frame}")
        return read_image(self.files[frame], flags, max_pixels)


class VideoFrames:
    """The frames of one video file, `count` of them expected at `width` x `height` (at least `count` unless
    `exact`)."""

    def __init__(self, path: Path, width: int, height: int, count: int, what: str, exact: bool = True):
        self.path = path
        self.width, self.height, self.count = width, height, count
        self._what = what
        self._lock = threading.Lock()
        self._capture: cv2.VideoCapture | None = None
        self._next = 0  # the frame the open capture decodes next
        self._decoded: OrderedDict[int, np.ndarray] = OrderedDict()
        self.restarts = 0  # decodes from the start again (a frame asked for after the window passed it)
        size, declared = _declared(self._open())
        if size != (width, height):
            raise CaptureError(f"{path}: the video's frames are {size[0]}x{size[1]} (WxH), but the calibration gives "
                               f"{width}x{height} for {what}; not decoded")
        if declared > count and not exact:
            self.count = declared
        elif declared > 0 and declared != count:
            shorter = "shorter than" if declared < count else "longer than"
            raise CaptureError(f"{path}: the video declares {declared} frames, {shorter} the {count} frames of body "
                               f"parameters (frame i of the video is frame i of the parameters); frame counts disagree")

    @property
    def frames(self) -> range:
        return range(self.count)

    def _open(self) -> cv2.VideoCapture:
        try:
            require_regular_file(self.path, CaptureError, f"a video of {self._what}")
        except FileNotFoundError:
            raise CaptureError(f"{self.path}: video not found") from None
        capture = cv2.VideoCapture(str(self.path))
        if not capture.isOpened():
            raise CaptureError(f"{self.path}: OpenCV cannot open it as a video (expected a video of {self._what})")
        return capture

    def read(self, frame: int, flags: int, max_pixels: int) -> np.ndarray:
        """The frame as BGR (IMREAD_COLOR) or its largest channel (IMREAD_GRAYSCALE, masks)."""
        if not 0 <= frame < self.count:
            raise CaptureError(f"{self.path}: no frame {frame} (the video holds frames 0..{self.count - 1})")
        if self.width * self.height > max_pixels:
            raise CaptureError(f"{self.path}: frames of {self.width}x{self.height} exceed {max_pixels:,} pixels")
        with self._lock:
            image = self._decoded.get(frame)
            if image is None:
                image = self._decode_to(frame)
        return image.max(axis=2) if flags == cv2.IMREAD_GRAYSCALE else image

    def _decode_to(self, frame: int) -> np.ndarray:
        if self._capture is None or frame < self._next:
            if self._capture is not None:
                self._capture.release()
                self.restarts += 1
            self._capture, self._next = self._open(), 0
        while self._next <= frame:
            if not self._capture.grab():
                raise CaptureError(f"{self.path}: the video ends after {self._next} frames, shorter than the "
                                   f"{self.count} frames of body parameters; frame counts disagree")
            if frame - self._next < VIDEO_WINDOW:
                ok, image = self._capture.retrieve()
                if not ok or image is None or image.shape[:2] != (self.height, self.width) or image.ndim != 3:
                    raise CaptureError(f"{self.path}: frame {self._next} does not decode to a {self.width}x"
                                       f"{self.height} colour image")
                image.setflags(write=False)
                self._decoded[self._next] = image
                while len(self._decoded) > VIDEO_WINDOW:
                    self._decoded.popitem(last=False)
            self._next += 1
        return self._decoded[frame]


def _declared(capture: cv2.VideoCapture) -> tuple[tuple[int, int], int]:
    """((width, height), frame count) a video's container declares (count 0: unknown); releases the capture."""
    try:
        size = (int(capture.get(cv2.CAP_PROP_FRAME_WIDTH)), int(capture.get(cv2.CAP_PROP_FRAME_HEIGHT)))
        return size, max(int(capture.get(cv2.CAP_PROP_FRAME_COUNT)), 0)
    finally:
        capture.release()


def video_in_place_of(folder: Path) -> Path | None:
    """The one video `folder.<mp4|mkv|avi|mov>` that stands for the frame folder `folder`, or None."""
    videos = [folder.with_name(folder.name + suffix) for suffix in VIDEO_SUFFIXES]
    videos = [video for video in videos if video.exists()]
    if len(videos) > 1:
        raise CaptureError(f"{folder}: {len(videos)} videos stand for this folder ({[v.name for v in videos]}); "
                           "keep one")
    return videos[0] if videos else None


def video_size(path: Path) -> tuple[int, int]:
    """(width, height) of a video's frames as its container declares them."""
    try:
        require_regular_file(path, CaptureError, "a video")
    except FileNotFoundError:
        raise CaptureError(f"{path}: video not found") from None
    capture = cv2.VideoCapture(str(path))
    if not capture.isOpened():
        raise CaptureError(f"{path}: OpenCV cannot open it as a video")
    return _declared(capture)[0]


def camera_frames(folder: Path, pattern: str, expected: str, width: int, height: int, count: int,
                  what: str, exact: bool = True) -> FrameFiles | VideoFrames:
    """The frames of `folder`, or of the one video `folder.<mp4|mkv|avi|mov>` that stands in its place (`count`
    frames, at least `count` unless `exact`); CaptureError naming the folder when neither is there or both hold
    frames."""
    video = video_in_place_of(folder)
    files = FrameFiles(folder, pattern, expected) if folder.is_dir() else None
    if video is not None:
        if files is not None and files.files:
            raise CaptureError(f"{folder}: holds {len(files.files)} frame files and the video {video} stands "
                               "for it too; keep either the frames or the video")
        return VideoFrames(video, width, height, count, what, exact)
    if files is None:
        raise CaptureError(f"{folder}: folder of {what} not found, nor a video {folder.name}.mp4 (or "
                           f"{', '.join(VIDEO_SUFFIXES[1:])}) beside it; expected {expected}")
    return files


def read_missing_list(path: Path, cameras, suffixes=IMAGE_SUFFIXES) -> set[tuple[str, int]]:
    """(camera, frame) pairs of a missing-files list (`<camera>/<frame>.jpg` a line, / or \\ separators, any folder
    before it), as THuman4 and AvatarReX write them; empty when the file is absent."""
    if not path.exists():
        return set()
    require_regular_file(path, CaptureError, "a list of missing files, one path a line")
    if path.stat().st_size > 64 * 2**20:
        raise CaptureError(f"{path}: {path.stat().st_size:,} bytes, more than a list of missing files holds; not read")
    pairs = set()
    for number, line in enumerate(path.read_text(errors="replace").splitlines(), start=1):
        line = line.strip()
        if not line:
            continue
        parts = [p for p in line.replace("\\", "/").split("/") if p]
        stem, _, suffix = parts[-1].rpartition(".")
        if len(parts) < 2 or parts[-2] not in cameras or not stem.isdigit() or f".{suffix.lower()}" not in suffixes:
            raise CaptureError(f"{path}:{number}: expected a path ending in <camera>/<frame>.jpg with a calibrated "
                               f"camera, found {line!r}")
        pairs.add((parts[-2], int(stem)))
    return pairs


class FramesCapture:
    """A `RawCapture` over each camera's images and masks as `FrameFiles` or `VideoFrames`: the readers set
    `source`, `cameras`, `frames` and `params`, then `_attach` the frames."""

    source: Path
    cameras: dict
    frames: list[int]
    layout = ""  # the expected tree, for messages
    # Masks whose foreground is any value above 0 (EasyMocap's); else THuman4's 0..255 mattes, person above 128.
    nonzero_masks = False

    def _attach(self, images: dict, masks: dict, missing: set[tuple[str, int]], extra_frames: bool = False) -> None:
        """Every frame with parameters must have an image and a mask, or be listed missing; frames beyond the
        parameters are an error unless `extra_frames` (a fit of part of a sequence)."""
        self._images, self._masks, self._missing = images, masks, missing
        wanted = set(self.frames)
        for kind, sources in (("images", images), ("masks", masks)):
            for camera, frames in sources.items():
                have = set(frames.frames)
                absent = sorted(wanted - have - {f for c, f in missing if c == camera})
                if absent:
                    raise CaptureError(f"{frames.path}: {len(absent)} of the {len(wanted)} frames with body parameters "
                                       f"have no {kind[:-1]} (first: {absent[:5]}); frame counts disagree (expected "
                                       f"{self.layout})")
                extra = sorted(have - wanted)
                if extra and not extra_frames:
                    raise CaptureError(f"{frames.path}: {len(extra)} frame(s) have no body parameters (first: "
                                       f"{extra[:5]}; parameters for frames {brief_range(self.frames)}); frame counts "
                                       "disagree")

    def has_frame(self, camera: str, frame: int) -> bool:
        self._camera(camera)
        return ((camera, frame) not in self._missing and frame in self._images[camera].frames
                and frame in self._masks[camera].frames)

    def read_image(self, camera: str, frame: int) -> np.ndarray:
        source = self._images[self._camera(camera).name]
        image = source.read(frame, cv2.IMREAD_COLOR, self._pixels(camera))
        self._check_size(image, camera, source, frame)
        return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)

    def read_mask(self, camera: str, frame: int) -> np.ndarray:
        source = self._masks[self._camera(camera).name]
        mask = source.read(frame, cv2.IMREAD_GRAYSCALE, self._pixels(camera))
        self._check_size(mask, camera, source, frame)
        if self.nonzero_masks:
            return np.where(mask > 0, 255, 0).astype(np.uint8)
        return check_matte(mask, f"{source.path} (frame {frame})")

    def _camera(self, camera: str):
        if camera not in self.cameras:
            raise CaptureError(f"{self.source}: unknown camera {camera!r}; cameras are {list(self.cameras)}")
        return self.cameras[camera]

    def _pixels(self, camera: str) -> int:
        return self.cameras[camera].width * self.cameras[camera].height

    def _check_size(self, image: np.ndarray, camera: str, source, frame: int) -> None:
        cam = self.cameras[camera]
        if image.shape[:2] != (cam.height, cam.width):
            raise CaptureError(f"{source.path} (frame {frame}): image is {image.shape[1]}x{image.shape[0]} (WxH), but "
                               f"the calibration gives {cam.width}x{cam.height} for camera {camera}")


def bounded_file(path: Path, expected: str, missing: str, max_bytes: int, holds: str) -> None:
    """CaptureError unless `path` is a regular file (`expected`) of at most `max_bytes`: `missing` words its absence,
    `holds` what a file of that kind holds at most."""
    try:
        require_regular_file(path, CaptureError, expected)
    except FileNotFoundError:
        raise CaptureError(f"{path}: {missing}") from None
    size = path.stat().st_size
    if size > max_bytes:
        raise CaptureError(f"{path}: {size:,} bytes, more than {holds}; not read")


def relative_folder(value, what: str, where: str) -> str:
    """`value` if it is a relative folder path whose every component is one safe name (never absolute, never
    `..`, never hidden), else CaptureError naming `where` and `what` it is."""
    if not isinstance(value, str) or not value:
        raise CaptureError(f"{where}: {what} must be a relative folder path, found {value!r}")
    for part in value.split("/"):
        safe_name(part, f"folder in {what} ({value!r})", where, CaptureError)
    return value


def brief_range(frames: list[int]) -> str:
    return f"{frames[0]}..{frames[-1]}" if frames else "none"

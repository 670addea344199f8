"""Training batches: K random timesteps x V random views of the train split, images held as uint8 tensors.

The sampling of Section 3.5 / 3.6 (4 views x 5 timesteps per iteration); no paper equation.
"""
from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
import torch
from tqdm import tqdm


@dataclass
class ViewBatch:
    """Views of one timestep that share an image size."""

    timestep: int  # index into the training frames
    cameras: list[str]
    viewmats: torch.Tensor  # (V, 4, 4) world-to-camera
    Ks: torch.Tensor  # (V, 3, 3)
    images: torch.Tensor  # (V, H, W, 3) float in [0, 1]
    masks: torch.Tensor  # (V, H, W) bool
    width: int
    height: int


class CaptureViews:
    """Images, masks and cameras of (camera, frame) pairs of a capture, loaded once onto `device`."""

    def __init__(self, capture, cameras: list[str], frames: list[int], device: torch.device | str, desc: str = "load views"):
        self.capture = capture
        self.cameras = list(cameras)
        self.frames = list(frames)
        self.device = torch.device(device)
        self.viewmats = {c: torch.as_tensor(capture.cameras[c].viewmat(), dtype=torch.float32, device=self.device) for c in cameras}
        self.Ks = {c: torch.as_tensor(capture.cameras[c].K, dtype=torch.float32, device=self.device) for c in cameras}
        pairs = [(c, f) for f in self.frames for c in self.cameras]

        def load(pair):
            cam, frame = pair
            image = np.round(capture.image(cam, frame) * 255).astype(np.uint8)
            return torch.from_numpy(image), torch.from_numpy(np.asarray(capture.mask(cam, frame), dtype=bool))

        # Decoding releases the GIL (OpenCV), so threads load in parallel.
        with ThreadPoolExecutor(max_workers=min(16, max(1, len(pairs)))) as pool:
            loaded = list(tqdm(pool.map(load, pairs), total=len(pairs), desc=desc, leave=False))
        self.images = {pair: (img.to(self.device), msk.to(self.device)) for pair, (img, msk) in zip(pairs, loaded)}

    def batch(self, timestep: int, cameras: list[str]) -> list[ViewBatch]:
        """The views of frame `self.frames[timestep]` seen by `cameras`, grouped by image size."""
        frame = self.frames[timestep]
        groups: dict[tuple[int, int], list[str]] = {}
        for cam in cameras:
            h, w = self.images[(cam, frame)][0].shape[:2]
            groups.setdefault((w, h), []).append(cam)
        out = []
        for (w, h), cams in groups.items():
            images = torch.stack([self.images[(c, frame)][0] for c in cams]).float() / 255
            masks = torch.stack([self.images[(c, frame)][1] for c in cams])
            out.append(ViewBatch(timestep, cams, torch.stack([self.viewmats[c] for c in cams]),
                                 torch.stack([self.Ks[c] for c in cams]), images, masks, w, h))
        return out


def sample_batch(generator: torch.Generator, num_timesteps: int, cameras: list[str], timesteps: int, views: int) -> list[tuple[int, list[str]]]:
    """K distinct random timesteps, each with V distinct random cameras (fewer when fewer exist)."""
    steps = torch.randperm(num_timesteps, generator=generator)[: min(timesteps, num_timesteps)].tolist()
    picks = []
    for step in steps:
        order = torch.randperm(len(cameras), generator=generator)[: min(views, len(cameras))].tolist()
        picks.append((step, [cameras[i] for i in order]))
    return picks

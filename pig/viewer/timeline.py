"""What the viewer's timeline plays: a motion clip brought into the capture's frame as `animate` brings it, or
the avatar's training poses; each entry's splats at a level of detail through `AvatarDriver`.

A motion frame takes the driver's real-time path (the nearest training timestep's decoded splats, the frame's
pose driving the transport). A training timestep is that timestep exactly: its refined pose and translation,
its own decoded splats. Both read the decoder outputs of every training timestep, computed once per level
(`AvatarDriver.decoded_all`), when they fit the driver's budget; otherwise the driver decodes per timestep.
"""
from __future__ import annotations

from dataclasses import fields
from pathlib import Path

import numpy as np
import torch

from pig.avatar.decoders import DecodedAnchors
from pig.avatar.driver import AvatarDriver
from pig.body.motion import align_motion, capture_frame, read_motion


class Timeline:
    """The frames of `motion_path` (aligned to the capture's up axis, ground and centre) or, without one, the
    avatar's training timesteps, on the model of `driver`."""

    def __init__(self, driver: AvatarDriver, motion_path: Path | None = None):
        self.driver = driver
        model = driver.model
        self.up, ground, self.centre = capture_frame(model)
        if motion_path is None:
            self.motion = None
            self.fps = 30.0
            self.length = model.num_timesteps
            self.source = "training poses"
        else:
            motion = read_motion(motion_path, hands_mean=model.body_model.hands_mean.cpu().numpy())
            self.motion = align_motion(motion, model.body_model, driver.refined()[0].cpu(), self.up, ground, self.centre)
            self.fps = float(self.motion.fps)
            self.length = self.motion.num_frames
            self.source = str(motion_path)

    def timestep(self, index: int) -> int | None:
        """The training timestep shown at `index` (None for a motion frame)."""
        return None if self.motion is not None else int(index)

    @torch.no_grad()
    def gaussians(self, lod: int, index: int) -> tuple[torch.Tensor, ...]:
        """(means, quats, scales, opacities, sh) of timeline entry `index` at level `lod`. On CUDA they may be a
        frame graph's outputs, overwritten by the next call: use them before asking for another frame."""
        if not 0 <= index < self.length:
            raise ValueError(f"timeline index must lie in 0..{self.length - 1}, got {index}")
        driver = self.driver
        if self.motion is not None:
            return driver.gaussians(lod, self.motion.full_pose[index], self.motion.transl[index])
        if not driver.frame_graph_fits(lod):
            return driver.gaussians(lod, timestep=index)
        stacked = driver.decoded_all(lod)
        decoded = DecodedAnchors(*(getattr(stacked, f.name)[index : index + 1] for f in fields(DecodedAnchors)))
        centres, rotation = driver.transport(lod, driver.body(index))
        g = driver.splats(centres, rotation, decoded)
        return g.means[0], g.quats[0], g.scales[0], g.opacities[0], g.sh[0]

    def bounds(self) -> tuple[np.ndarray, float]:
        """(centre (3,), size in metres) of the body over the timeline, for framing the orbit."""
        from pig.avatar.animation import subject_bounds

        driver = self.driver
        if self.motion is not None:
            poses, transl = self.motion.full_pose, self.motion.transl
        else:
            poses, transl = (t.detach().cpu().double().numpy() for t in (driver.refined()[1], driver.model.transl))
        return subject_bounds(driver.model, driver.refined()[0], poses, transl)

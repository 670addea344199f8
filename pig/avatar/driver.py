"""Pose-driven rendering of a fitted avatar: per frame only the work that depends on the frame.

`AvatarModel.forward` recomputes everything for every frame: grid features of all anchors (Eq. 1, the
refiner's z_bar), the refiner over all training timesteps (Eqs. 12-14), then body, transport (Eqs. 2-3) and
decoders (Eqs. 6-9). With the model fixed, the driver keeps
- the canonical anchors x (one solve of their preconditioning) and their grid features, once per LOD;
- the refined betas and the refined pose of every training timestep, once;
- the nearest training timestep of a query pose (Section 4.1), once per pose (keyed by its bytes);
- the decoded attributes of (LOD, timestep), which depend on z, gamma(t) and the level only, for the
  `decoded_cache` most recent pairs: consecutive poses near one training pose skip the decoders.
Per frame there remain the posed body, the transport of the level's anchors and Eqs. 10-11; the parts
(`nearest_timestep`, `body`, `transport`, `decoded`, `splats`) are public so that they can be timed apart.

The real-time path (`frame_graph=True`) goes further for pose-driven frames: the decoders' outputs of every
training timestep at the level are computed once and held stacked on the device (while the levels held fit in
`decoded_budget_bytes` together), and so is the body's rest shape (shape and expression blend, rest joints) of every
training timestep, so a frame is pose -> nearest timestep (an argmin on the device) -> posed body ->
transport -> a gather of the decoded timestep -> Eqs. 10-11, with no host synchronisation. On CUDA that
function is compiled and captured once per level as a CUDA graph: the frame's hundreds of small kernels
(the 55-joint chain alone is 55 matrix products) then cost one launch. Over the budget the frame decodes its
timestep itself (the decoders inside the graph), and a training timestep in its refined pose (`timestep_frame`,
the novel-view split's frames) is a frame of its own graph. `compile_frames=False` captures the frames as they are
launched, without torch.compile: a render stage's few thousand frames then pay no compilation.
"""
from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable
from dataclasses import fields

import numpy as np
import torch

from pig.body.rotation import axis_angle_to_matrix, geodesic_distance
from pig.cuda_graphs import capture

from .decoders import DecodedAnchors
from .model import AvatarModel, Gaussians
from .nearest_pose import BODY_SLICE


class AvatarDriver:
    """Gaussians of a fitted `AvatarModel` for a level of detail and a pose, with per-avatar work cached.

    The model must not change afterwards (the caches hold its outputs); it is put in eval mode and all
    work runs without gradients. Results equal `model.gaussians` up to float rounding.
    """

    def __init__(self, model: AvatarModel, decoded_cache: int = 4, pose_cache: int = 4096, frame_graph: bool = False,
                 decoded_budget_bytes: int = 8 << 30, compile_frames: bool = True):
        if decoded_cache < 0 or pose_cache < 0:
            raise ValueError(f"AvatarDriver: cache sizes must be >= 0, got decoded_cache={decoded_cache}, pose_cache={pose_cache}")
        self.model = model.eval()
        self.decoded_cache, self.pose_cache = decoded_cache, pose_cache
        self.frame_graph, self.decoded_budget_bytes = frame_graph, decoded_budget_bytes
        self.compile_frames = compile_frames
        self._decoded_all: dict[int, DecodedAnchors] = {}  # lod -> outputs (T, n, ...) of every training timestep
        self._frames: dict[tuple[int, str], "_FrameGraph"] = {}  # (lod, "pose" | "pose+transl" | "timestep")
        self._train_rotations: torch.Tensor | None = None  # (T, 21, 3, 3) body-joint rotations of the training poses
        self._anchors: torch.Tensor | None = None
        self._features: dict[int, torch.Tensor] = {}  # lod -> z (n, d)
        self._z_mean: torch.Tensor | None = None
        self._refined: tuple[torch.Tensor, torch.Tensor] | None = None  # betas (nb,), pose (T, 55, 3)
        self._rest: tuple[torch.Tensor, torch.Tensor] | None = None  # shaped vertices (T, V, 3), rest joints (T, 55, 3)
        self._nearest: OrderedDict[bytes, int] = OrderedDict()
        self._decoded: OrderedDict[tuple[int, int], DecodedAnchors] = OrderedDict()

    @property
    def device(self) -> torch.device:
        return self.model.pose_init.device

    # ---- once per avatar / per LOD ----

    @torch.no_grad()
    def anchors(self) -> torch.Tensor:
        """Canonical anchors (N, 3), solved once."""
        if self._anchors is None:
            self._anchors = self.model.canonical_anchors().detach()
        return self._anchors

    @torch.no_grad()
    def features(self, lod: int) -> torch.Tensor:
        """Grid features (n, d) of the level's anchors. With a refiner, the first call evaluates the grid at
        all anchors (z_bar needs them) and serves every level from it; without, one evaluation per level."""
        self._check_lod(lod)
        if lod not in self._features:
            model = self.model
            finest = model.num_levels - 1
            if model.refiner.net is not None:
                z_all, self._z_mean = model.anchor_features(self.anchors(), finest)
                self._features = {level: z_all[:n] for level, n in enumerate(model.level_sizes)}
            else:
                self._features[lod] = model.anchor_features(self.anchors(), lod)[0]
        return self._features[lod]

    @torch.no_grad()
    def rest_shapes(self) -> tuple[torch.Tensor, torch.Tensor]:
        """The body's rest shape at every training timestep (refined betas, the timestep's expression): shaped
        vertices (T, V, 3) and rest joints (T, 55, 3), computed once; a frame then only poses them."""
        if self._rest is None:
            betas, _ = self.refined()
            body, expression = self.model.body_model, self.model.expression
            # One timestep at a time: the per-pose path's products of the same shapes, so the same rounding.
            parts = [body.rest_shape(1, betas, expression[t : t + 1]) for t in range(self.model.num_timesteps)]
            self._rest = tuple(torch.cat(tensors) for tensors in zip(*parts))
        return self._rest

    @torch.no_grad()
    def refined(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Refined betas (nb,) and the refined pose (T, 55, 3) of every training timestep, computed once."""
        if self._refined is None:
            model = self.model
            if model.refiner.net is not None:
                self.features(0)  # sets z_bar
            steps = torch.arange(model.num_timesteps, device=self.device)
            self._refined = model.refined_params(steps, self._z_mean)
        return self._refined

    # ---- per pose / per frame ----

    @torch.no_grad()
    def nearest_timestep(self, pose) -> int:
        """Training timestep nearest to a (55, 3) axis-angle pose (numpy or tensor), once per distinct pose."""
        query = self._pose(pose)
        key = query.cpu().numpy().tobytes()
        if key in self._nearest:
            self._nearest.move_to_end(key)
            return self._nearest[key]
        timestep = self.model.nearest_timestep(query)
        if self.pose_cache:
            self._nearest[key] = timestep
            while len(self._nearest) > self.pose_cache:
                self._nearest.popitem(last=False)
        return timestep

    @torch.no_grad()
    def body(self, timestep: int, pose=None, transl=None) -> torch.Tensor:
        """Posed body vertices (1, V, 3): the refined shape in `pose` (55, 3) or the timestep's refined pose,
        moved by `transl` (3,) or the timestep's translation; the timestep's expression."""
        model = self.model
        betas, poses = self.refined()
        step = slice(timestep, timestep + 1)
        full_pose = poses[step] if pose is None else self._pose(pose)[None].to(poses)
        translation = model.transl[step] if transl is None else self._transl(transl)
        return model.body_model(full_pose, betas, model.expression[step], translation).vertices

    @torch.no_grad()
    def transport(self, lod: int, vertices: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Posed centres (1, n, 3) and transport rotations (1, n, 3, 3) of the level's anchors."""
        self._check_lod(lod)
        return self.model.transport(self.anchors(), vertices, lod)

    @torch.no_grad()
    def decoded(self, lod: int, timestep: int) -> DecodedAnchors:
        """Decoder outputs (1, n, ...) of the level's anchors at a timestep; the recent pairs are kept."""
        key = (lod, timestep)
        if key in self._decoded:
            self._decoded.move_to_end(key)
            return self._decoded[key]
        steps = torch.tensor([timestep], device=self.device)
        out = self.model.decode(self.features(lod), steps, lod)
        if self.decoded_cache:
            self._decoded[key] = out
            while len(self._decoded) > self.decoded_cache:
                self._decoded.popitem(last=False)
        return out

    def splats(self, centres: torch.Tensor, rotation: torch.Tensor, decoded: DecodedAnchors) -> Gaussians:
        return self.model.splats(centres, rotation, decoded)

    # ---- the real-time path: every timestep decoded, one function per frame ----

    def decoded_all_bytes(self, lod: int) -> int:
        """Device memory that the decoded outputs of every training timestep at `lod` take."""
        model = self.model
        per_anchor = 3 + 4 + 3 + 1 + 3 * (model.cfg.sh_degree + 1) ** 2
        return model.num_timesteps * model.level_sizes[lod] * per_anchor * model.x_init.element_size()

    @torch.no_grad()
    def decoded_all(self, lod: int, chunk: int = 8) -> DecodedAnchors:
        """Decoder outputs (T, n, ...) of the level's anchors at every training timestep, computed once."""
        self._check_lod(lod)
        if lod not in self._decoded_all:
            steps = torch.arange(self.model.num_timesteps, device=self.device)
            parts = [self.model.decode(self.features(lod), steps[i:i + chunk], lod) for i in range(0, len(steps), chunk)]
            self._decoded_all[lod] = DecodedAnchors(*(torch.cat([getattr(p, f.name) for p in parts]).float()
                                                      for f in fields(DecodedAnchors)))
        return self._decoded_all[lod]

    def frame_graph_fits(self, lod: int) -> bool:
        """Whether the decoded outputs of every timestep at `lod` are held or fit the budget beside the levels already
        held (the budget bounds them all together): frames then gather their timestep's instead of decoding it."""
        if lod in self._decoded_all:
            return True
        held = sum(self.decoded_all_bytes(level) for level in self._decoded_all)
        return held + self.decoded_all_bytes(lod) <= self.decoded_budget_bytes

    def _frame(self, lod: int, pose: torch.Tensor | None, transl: torch.Tensor | None,
               step: torch.Tensor | None = None) -> tuple[torch.Tensor, ...]:
        """One frame on the device: (means, quats, scales, opacities, sh) and the timestep (1,). Pose-driven (`step`
        None): `pose` (55, 3) and the training timestep nearest to it; else training timestep `step` (1,) in its
        refined pose. The timestep's decoded attributes are a gather from `decoded_all` where it holds the level,
        else decoded here. Every operation is a device kernel with static shapes, so the function can be captured
        as a graph."""
        model = self.model
        if step is None:
            query = axis_angle_to_matrix(pose[BODY_SLICE])  # (21, 3, 3)
            step = geodesic_distance(query[None], self._train_rotations).sum(-1).argmin()[None]  # ties -> earliest
            full_pose = pose[None]
        else:
            full_pose = self.refined()[1][step]
        shaped, joints_rest = self.rest_shapes()
        translation = model.transl[step] if transl is None else transl
        if lod in self._decoded_all:
            decoded = DecodedAnchors(*(getattr(self._decoded_all[lod], f.name)[step] for f in fields(DecodedAnchors)))
        else:
            decoded = model.decode(self.features(lod), step, lod)
        g = model.posed_splats(self.anchors(), lod, full_pose, None, None, translation, decoded, sync_free=True,
                               rest=(shaped[step], joints_rest[step]))
        return g.means[0], g.quats[0], g.scales[0], g.opacities[0], g.sh[0], step

    def _prepare_frames(self, lod: int) -> None:
        """Fills the per-avatar and per-LOD caches that a frame reads, outside any graph: the frame only reads them."""
        if self._train_rotations is None:
            self._train_rotations = axis_angle_to_matrix(self.model.pose_init[:, BODY_SLICE])
        self.refined()
        self.features(lod)
        self.rest_shapes()
        if self.frame_graph_fits(lod):
            self.decoded_all(lod)

    def _graph(self, lod: int, kind: str, frame: Callable[[torch.Tensor], tuple[torch.Tensor, ...]], size: int,
               dtype: torch.dtype) -> "_FrameGraph":
        key = (lod, kind)
        if key not in self._frames:
            self._frames[key] = _FrameGraph(frame, size, dtype, self.device, self.compile_frames)
        return self._frames[key]

    @torch.no_grad()
    def posed_frame(self, lod: int, pose, transl=None) -> tuple[tuple[torch.Tensor, ...], torch.Tensor]:
        """The real-time path: ((means, quats, scales, opacities, sh), timestep (1,)) for a (55, 3) pose, equal to
        `gaussians(lod, pose, transl)`. On CUDA the tensors are a graph's outputs, overwritten by the next call
        at this level: consume (render) or clone them first."""
        self._check_lod(lod)
        self._prepare_frames(lod)
        if self.device.type != "cuda":
            *splats, step = self._frame(lod, self._pose(pose), None if transl is None else self._transl(transl))
            return tuple(splats), step
        # Host inputs stay on the host until the graph's one asynchronous copy (_FrameGraph.run).
        parts = [self._pose(pose, keep_device=True)]
        if transl is not None:
            parts.append(self._transl(transl, keep_device=True))

        def frame(inputs: torch.Tensor) -> tuple[torch.Tensor, ...]:  # pose values, then the translation's if any
            translation = None if transl is None else inputs[55 * 3 :].view(1, 3)
            return self._frame(lod, inputs[: 55 * 3].view(55, 3), translation)

        kind = "pose" if transl is None else "pose+transl"
        graph = self._graph(lod, kind, frame, 55 * 3 + 3 * (transl is not None), self.model.pose_init.dtype)
        *splats, step = graph.run(*parts)
        return tuple(splats), step

    @torch.no_grad()
    def timestep_frame(self, lod: int, timestep: int) -> tuple[torch.Tensor, ...]:
        """(means, quats, scales, opacities, sh) of training timestep `timestep` in its refined pose, equal to
        `gaussians(lod, timestep=timestep)`: the frame-graph path of a training frame. On CUDA the tensors are a
        graph's outputs, overwritten by the next call at this level: consume (render) or clone them first."""
        self._check_lod(lod)
        self._check_timestep(timestep)
        self._prepare_frames(lod)
        if self.device.type != "cuda":
            return self._frame(lod, None, None, torch.tensor([int(timestep)], device=self.device))[:5]
        graph = self._graph(lod, "timestep", lambda inputs: self._frame(lod, None, None, inputs), 1, torch.int64)
        return graph.run(np.array([int(timestep)], dtype=np.int64))[:5]

    def gaussians(self, lod: int, pose=None, transl=None, timestep: int | None = None) -> tuple[torch.Tensor, ...]:
        """(means, quats, scales, opacities, sh) of one frame, as `AvatarModel.gaussians` returns them.

        Without `pose`, the training timestep `timestep` in its refined pose. With `pose` (55, 3) (and
        optionally `transl` (3,)), the pose drives the transport with the refined shape while gamma(t)
        comes from `timestep`, by default the training timestep nearest to `pose`.
        """
        self._check_lod(lod)
        if timestep is None:
            if pose is None:
                raise ValueError("AvatarDriver.gaussians needs a timestep, a pose, or both")
            if self.frame_graph:
                return self.posed_frame(lod, pose, transl)[0]
            timestep = self.nearest_timestep(pose)
        self._check_timestep(timestep)
        timestep = int(timestep)
        if self.frame_graph and pose is None and transl is None:
            return self.timestep_frame(lod, timestep)
        centres, rotation = self.transport(lod, self.body(timestep, pose, transl))
        g = self.splats(centres, rotation, self.decoded(lod, timestep))
        return g.means[0], g.quats[0], g.scales[0], g.opacities[0], g.sh[0]

    def forget_poses(self) -> None:
        """Drop what is cached per pose (nearest timesteps, decoded timesteps); per-LOD work stays."""
        self._nearest.clear()
        self._decoded.clear()

    # ---- input checks ----

    def _check_lod(self, lod: int) -> None:
        if not 0 <= lod < self.model.num_levels:
            raise ValueError(f"lod must lie in 0..{self.model.num_levels - 1}, got {lod}")

    def _check_timestep(self, timestep: int) -> None:
        if not 0 <= int(timestep) < self.model.num_timesteps:
            raise ValueError(f"timestep must lie in 0..{self.model.num_timesteps - 1}, got {timestep}")

    def _pose(self, pose, keep_device: bool = False) -> torch.Tensor | np.ndarray:
        """A checked (55, 3) pose in the model's dtype on the model's device; with `keep_device` a tensor stays
        where it lies and anything else stays a host array (165,) for the frame graph's staging buffer."""
        return self._checked(pose, (55, 3), "a (55, 3) axis-angle pose", "pose", keep_device)

    def _transl(self, transl, keep_device: bool = False) -> torch.Tensor | np.ndarray:
        return self._checked(transl, (1, 3), "a (3,) translation", "translation", keep_device)

    def _checked(self, value, shape: tuple[int, int], expected: str, what: str, keep_device: bool):
        if keep_device and not torch.is_tensor(value):  # numpy checks: a few microseconds less of host work a frame
            array = np.asarray(value)
            if array.size != shape[0] * shape[1]:
                raise ValueError(f"AvatarDriver: expected {expected}, found shape {array.shape}")
            if not np.isfinite(array).all():
                raise ValueError(f"AvatarDriver: the {what} holds NaN or infinite values")
            return array.reshape(-1)
        tensor = torch.as_tensor(np.asarray(value) if not torch.is_tensor(value) else value)
        if tensor.numel() != shape[0] * shape[1]:
            raise ValueError(f"AvatarDriver: expected {expected}, found shape {tuple(tensor.shape)}")
        if not bool(torch.isfinite(tensor).all()):  # checked where it lies: host values cost no device sync
            raise ValueError(f"AvatarDriver: the {what} holds NaN or infinite values")
        return tensor.reshape(shape).to(dtype=self.model.pose_init.dtype, device=None if keep_device else self.device)


class _FrameGraph:
    """A frame function captured as a CUDA graph (compiled first, or as launched) that reads its inputs (a pose and
    translation, or a timestep) from one static device buffer. Host inputs reach it through a pinned staging buffer
    in one asynchronous copy: a frame costs no blocking transfer and no copy kernel before the replay."""

    def __init__(self, frame: Callable[[torch.Tensor], tuple[torch.Tensor, ...]], size: int, dtype: torch.dtype,
                 device: torch.device, compile_frame: bool):
        self.inputs = torch.zeros(size, dtype=dtype, device=device)
        self.staging = torch.zeros(size, dtype=dtype, pin_memory=True)
        self.staged = torch.cuda.Event()  # the last copy out of `staging` is done once this has passed
        self.staged.record()
        run = torch.compile(frame, dynamic=False) if compile_frame else frame
        self.graph, self.outputs = capture(lambda: run(self.inputs), device, warmups=2)

    def run(self, *parts) -> tuple[torch.Tensor, ...]:
        """Replay on `parts` (e.g. 55 x 3 pose values, then 3 translation values), written one after another into
        the input buffer: CUDA tensors, or host tensors or arrays."""
        if torch.is_tensor(parts[0]) and parts[0].is_cuda:
            self._fill(self.inputs, parts)
        else:
            self.staged.synchronize()  # the previous frame's copy may still be reading the staging buffer
            self._fill(self.staging.numpy(), parts)
            self.inputs.copy_(self.staging, non_blocking=True)
            self.staged.record()
        self.graph.replay()
        return self.outputs

    @staticmethod
    def _fill(buffer, parts) -> None:
        """Write the parts' values, flattened, one after another into a device tensor or a host array."""
        start = 0
        for part in parts:
            values = part.reshape(-1)
            buffer[start : start + len(values)] = values
            start += len(values)

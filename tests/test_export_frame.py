"""Export in the capture's frame: the demo motion's frames stand upright along canonical.ply's axis, on the ground.

The reference is the capture itself: the synthetic subject is y-up, and its ground is the lowest vertex of its own
training poses, posed here in float64 through the body model, apart from the code under test.
"""
import json

import numpy as np
import pytest
import torch

from pig.body.model import BodyModel
from pig.body.motion import DEMO_MOTION
from pig.data.capture import Capture
from pig.stages.export import main
from test_export import read_ply

FRAMES = "0:144:13"  # 12 frames spread over the clip


def _training_ground_and_centre(capture_dir):
    """(lowest vertex height along +y, mean root position) over the capture's training frames, in float64."""
    capture = Capture.load(capture_dir)
    rows = [capture.frames.index(f) for f in capture.split["train"]["frames"]]
    params = capture.params.select(rows)
    body = BodyModel.from_file(capture_dir / "body_model.npz", dtype=torch.float64)
    with torch.no_grad():
        out = body(torch.as_tensor(params.full_pose), torch.as_tensor(params.betas)[None],
                   torch.as_tensor(params.expression), torch.as_tensor(params.transl))
    return float(out.vertices[..., 1].min()), out.joints[:, 0].mean(0).numpy()


@pytest.mark.slow
def test_demo_motion_frames_stand_upright_like_canonical_on_the_capture_ground(tiny_fit, tmp_path):
    capture_dir, checkpoint = tiny_fit
    out = tmp_path / "export"
    assert main(["--checkpoint", str(checkpoint), "--output", str(out), "--motion", str(DEMO_MOTION),
                 "--frames", FRAMES, "--device", "cpu"]) == 0
    frames = list(range(*map(int, FRAMES.split(":"))))
    ground, root = _training_ground_and_centre(capture_dir)
    canonical = read_ply(out / "canonical.ply")[1]
    rest = np.stack([canonical["x"], canonical["y"], canonical["z"]], 1).astype(np.float64)
    # Head and feet: the anchors highest and lowest along canonical.ply's up axis (+y), followed through the frames
    # by their anchor ids (row i of every file and of the correspondences is anchor i).
    order = np.argsort(rest[:, 1])
    tenth = len(order) // 10
    feet, head = order[:tenth], order[-tenth:]
    canonical_axis = rest[head].mean(0) - rest[feet].mean(0)
    assert canonical_axis[1] / np.linalg.norm(canonical_axis) > 0.95
    positions = np.load(out / "correspondences.npz")["positions"].astype(np.float64)
    assert positions.shape[0] == len(frames)
    lowest = []
    for f, frame in enumerate(frames):
        ply = read_ply(out / f"frame_{frame:06d}.ply")[1]
        np.testing.assert_array_equal(np.stack([ply["x"], ply["y"], ply["z"]], 1), positions[f])
        axis = positions[f][head].mean(0) - positions[f][feet].mean(0)
        cosine = axis[1] / np.linalg.norm(axis)
        assert cosine > np.cos(np.radians(30)), f"frame {frame}: leans {np.degrees(np.arccos(cosine)):.0f} deg off +y"
        lowest.append(positions[f][:, 1].min())
        # Over the capture's subject: the frame's middle lies within 0.5 m of the training poses' mean root.
        middle = positions[f].mean(0)
        assert np.hypot(*(middle - root)[[0, 2]]) < 0.5, f"frame {frame}: {middle} is far from the capture's {root}"
    lowest = np.array(lowest)
    # On the ground: no frame sinks below it, and the clip's lowest frame touches it (splats lie on the body surface,
    # the alignment puts the clip's lowest body vertex on the ground).
    assert lowest.min() == pytest.approx(ground, abs=0.03)
    assert (lowest > ground - 0.03).all() and (lowest < ground + 0.3).all(), (lowest, ground)
    # Each file names its up axis in its header and in the sidecar.
    record = json.loads((out / "export.json").read_text())
    assert record["up_axis"] == "+y" and record["files"]["canonical.ply"]["up_axis"] == "+y"
    names = ["canonical.ply"] + [f"frame_{f:06d}.ply" for f in frames]
    assert sorted(record["files"]) == sorted(names)
    for name in names:
        header = (out / name).read_bytes().split(b"end_header\n")[0].decode("ascii").splitlines()
        assert [line for line in header if line.startswith("comment up_axis")] == ["comment up_axis +y"], name
        assert record["files"][name]["up_axis"] == "+y"
    assert record["ground"] == pytest.approx(ground, abs=0.03)

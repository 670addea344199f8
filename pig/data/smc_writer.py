"""Writer of the DNA-Rendering `.smc` layout: exports any `RawCapture` (the synthetic one included) to a
main file of encoded images and an `_annots.smc` with calibration, masks and SMPL-X fits (FORMATS.md).

The inverse of `pig.data.dna.DnaCapture`: world-to-camera -> camera-to-world `RT`, RGB -> BGR, and
flat-hand-mean poses -> the dataset's `flat_hand_mean=False` convention (subtracts `hands_mean`).

What the dataset's own reader (SMCReader of the DNA-Rendering repository) needs, and so is always written:
`Color_Calibration` for every camera (identity without a correction), `betas` with one row per frame
(it takes the frame count from them), and all actor attributes of the download page, `ethnicity` included.
"""
from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import h5py
import numpy as np
import torch

from pig.body.model import LEFT_HAND, NUM_JOINTS, RIGHT_HAND, BodyModel
from pig.data.dna import ANNOTS_SUFFIX, CALIBRATION, CAMERA_GROUPS, MASKS, SMPLX, bgr_matrix_to_rgb, model_gender
from pig.data.raw import CaptureError, RawCapture
from pig.progress import progress_bar
from pig._cli import add_common_arguments, run_cli
from pig._io import atomic_path

DNA_NUM_5MP = 48  # cams 0..47 are Camera_5mp in the released data, the rest Camera_12mp
# Actor facts an export cannot know; override with `actor=` / `--actor KEY=VALUE`. The download page
# lists ethnicity as one of yellow, white, black, brown: an export does not guess one.
PLACEHOLDER_AGE = 30
UNKNOWN_ETHNICITY = "unknown"
NORMAL_BMI = 22.0  # kg/m^2, middle of the normal range: the weight written for the body's height


def _encode(image: np.ndarray, ext: str, jpeg_quality: int) -> np.ndarray:
    params = [cv2.IMWRITE_JPEG_QUALITY, jpeg_quality] if ext in (".jpg", ".jpeg") else []
    ok, data = cv2.imencode(ext, image, params)
    if not ok:
        raise CaptureError(f"OpenCV could not encode a {image.shape} image as {ext}")
    return data.reshape(-1)


def _standing_height_cm(model: BodyModel, betas: np.ndarray) -> int:
    """Vertical (y, SMPL-X's up axis) extent of the shaped body in its rest pose, in centimetres."""
    body = model(torch.zeros(1, NUM_JOINTS, 3), torch.from_numpy(np.asarray(betas, dtype=np.float64)))
    heights = body.shaped_vertices[0, :, 1].detach().cpu().double().numpy()
    return int(round(100 * (heights.max() - heights.min())))


def _actor_attributes(capture: RawCapture, sequence: str, actor: dict | None, model: BodyModel, model_path) -> dict:
    """Root attributes of the main file: the download page's ints and strings (ids from `<actor>_<performance>`)."""
    actor_id, _, performance = sequence.partition("_")
    height = _standing_height_cm(model, capture.params.betas)
    values = {"actor_id": _int_if_digits(actor_id), "performance_id": _int_if_digits(performance or "00"),
              "age": PLACEHOLDER_AGE, "gender": model_gender(model_path) or "neutral", "height": height,
              "weight": int(round(NORMAL_BMI * (height / 100) ** 2)), "ethnicity": UNKNOWN_ETHNICITY}
    values.update(getattr(capture, "actor", None) or {})
    values.update(actor or {})
    return values


def _int_if_digits(text: str) -> int | str:
    return int(text) if text.isdigit() else text


def write_smc(capture: RawCapture, out_dir: str | Path, sequence: str, body_model: str | Path | BodyModel, *,
              num_5mp: int | None = None, image_ext: str = ".png", jpeg_quality: int = 95,
              actor: dict | None = None) -> tuple[Path, Path]:
    """Write `out_dir/<sequence>.smc` and `out_dir/annotations/<sequence>_annots.smc`; atomic per file.

    Cameras get ids 0..C-1 in the capture's order; the first `num_5mp` (default min(C, 48)) go to
    Camera_5mp, the rest to Camera_12mp. Frames become 0..N-1 in `capture.frames` order; frames the
    capture lacks for a camera are left out. `body_model`: the SMPL-X model whose `hands_mean` the file's
    `flat_hand_mean=False` poses refer to. `.png` (default) is lossless; `.jpg` uses `jpeg_quality`.
    `actor`: root attributes that replace the defaults (gender from the model file's name, else neutral;
    height of the shaped body in cm; the weight of a BMI of 22; placeholder age; ethnicity "unknown").
    """
    out_dir = Path(out_dir)
    names = list(capture.cameras)
    num_5mp = min(len(names), DNA_NUM_5MP) if num_5mp is None else num_5mp
    if not 0 <= num_5mp <= len(names):
        raise ValueError(f"num_5mp = {num_5mp}, expected 0..{len(names)} (the capture has {len(names)} cameras)")
    groups = {CAMERA_GROUPS[0]: list(enumerate(names))[:num_5mp], CAMERA_GROUPS[1]: list(enumerate(names))[num_5mp:]}
    model = body_model if isinstance(body_model, BodyModel) else BodyModel.from_file(body_model)
    hands_mean = model.hands_mean.detach().cpu().double().numpy()
    attributes = _actor_attributes(capture, sequence, actor, model, body_model)

    main_path = out_dir / f"{sequence}.smc"
    annots_path = out_dir / "annotations" / f"{sequence}{ANNOTS_SUFFIX}.smc"
    annots_path.parent.mkdir(parents=True, exist_ok=True)
    frames = list(capture.frames)
    total = len(names) * len(frames)
    with atomic_path(main_path) as tmp_main, atomic_path(annots_path) as tmp_annots:
        with h5py.File(tmp_main, "w") as main, h5py.File(tmp_annots, "w") as annots, \
                progress_bar(total=total, desc=f"write {sequence}.smc", unit="img") as progress:
            for key, value in attributes.items():
                main.attrs[key] = value
            calibration = annots.create_group(CALIBRATION)
            masks = annots.create_group(MASKS)
            for group_name, members in groups.items():
                if not members:
                    continue
                sizes = {(capture.cameras[n].width, capture.cameras[n].height) for _, n in members}
                if len(sizes) != 1:
                    raise CaptureError(f"{capture.source}: cameras of {group_name} differ in size {sorted(sizes)}; "
                                       "a .smc camera group has one resolution")
                width, height = sizes.pop()
                group = main.create_group(group_name)
                group.attrs["num_device"] = len(members)
                group.attrs["num_frame"] = len(frames)
                group.attrs["resolution"] = np.array([height, width], dtype=np.int64)
                for cam_id, name in members:
                    _write_camera(calibration.create_group(f"{cam_id:02d}"), capture.cameras[name])
                    color = group.create_group(f"{cam_id}/color")
                    mask = masks.create_group(f"{cam_id}/mask")
                    for index, frame in enumerate(frames):
                        progress.update()
                        if not capture.has_frame(name, frame):
                            continue
                        color[str(index)] = _encode(capture.read_image(name, frame)[..., ::-1], image_ext, jpeg_quality)
                        mask[str(index)] = _encode(capture.read_mask(name, frame), image_ext, jpeg_quality)
            _write_params(annots.create_group(SMPLX), capture, hands_mean)
    return main_path, annots_path


def _write_camera(group: h5py.Group, camera) -> None:
    world_to_cam = np.eye(4)
    world_to_cam[:3, :3] = camera.R
    world_to_cam[:3, 3] = camera.T
    group["K"] = np.asarray(camera.K, dtype=np.float64)
    group["D"] = np.asarray(camera.dist, dtype=np.float64).reshape(-1)
    group["RT"] = np.linalg.inv(world_to_cam)
    correction = np.eye(3) if camera.color_correction is None else bgr_matrix_to_rgb(camera.color_correction)
    group["Color_Calibration"] = np.asarray(correction, dtype=np.float64)


def _write_params(group: h5py.Group, capture: RawCapture, hands_mean: np.ndarray) -> None:
    params = capture.params
    pose = params.full_pose.astype(np.float64).copy()
    for part in (LEFT_HAND, RIGHT_HAND):
        pose[:, part] -= hands_mean[part]
    group["fullpose"] = pose
    group["betas"] = np.repeat(np.asarray(params.betas, dtype=np.float64)[None], len(pose), axis=0)
    group["expression"] = np.asarray(params.expression, dtype=np.float64)
    group["transl"] = np.asarray(params.transl, dtype=np.float64)
    group["scale"] = np.array([1.0])


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description="Export a capture to the DNA-Rendering .smc layout "
                                     "(<output>/<sequence>.smc and <output>/annotations/<sequence>_annots.smc).")
    parser.add_argument("--format", required=True, help="input capture format (e.g. thuman4, dna)")
    parser.add_argument("--input", required=True, type=Path, help="input capture root")
    parser.add_argument("--output", required=True, type=Path, help="output folder")
    parser.add_argument("--sequence", default="0000_00", help="sequence name <actor>_<performance>")
    parser.add_argument("--body-model", type=Path, default=None,
                        help="SMPL-X npz the capture's poses use (default: <input>/body_model.npz)")
    parser.add_argument("--num-5mp", type=int, default=None, help="cameras written to Camera_5mp (default min(C, 48))")
    parser.add_argument("--actor", action="append", default=[], metavar="KEY=VALUE",
                        help="root attribute of the main file, e.g. gender=female or age=41 (repeatable)")
    parser.add_argument("--jpeg", type=int, default=None, metavar="QUALITY", help="encode JPEG instead of PNG")
    add_common_arguments(parser)
    args = parser.parse_args(argv)
    actor = {}
    for item in args.actor:
        key, sep, value = item.partition("=")
        if not sep or not key:
            parser.error(f"--actor {item!r}: expected KEY=VALUE, e.g. ethnicity=white")
        actor[key] = _int_if_digits(value)
    from pig.data.formats import capture_format, open_capture

    body_model = args.body_model or args.input / "body_model.npz"
    if not Path(body_model).is_file():
        parser.error(f"body model {body_model} not found; pass --body-model PATH (SMPL-X npz)")
    options = {"body_model": body_model} if capture_format(args.format).needs_body_model else {}
    try:
        capture = open_capture(args.format, args.input, **options)
    except CaptureError as err:
        parser.exit(1, f"smc_writer: error: {err}\n")
    ext, quality = (".png", 95) if args.jpeg is None else (".jpg", args.jpeg)
    for path in write_smc(capture, args.output, args.sequence, body_model, num_5mp=args.num_5mp,
                          image_ext=ext, jpeg_quality=quality, actor=actor):
        print(path)


if __name__ == "__main__":
    raise SystemExit(run_cli(main))

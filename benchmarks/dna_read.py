"""Cost of reading DNA-Rendering frames (pig.data.dna): where the time of `read_image` goes at the real
frame size (2048 x 2448 JPEG in HDF5), and what reopening the .smc per read would add over keeping it open.

    python benchmarks/dna_read.py [--width 2048] [--height 2448] [--frames 4] [--repeats 7]
"""
from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import cv2
import h5py
import numpy as np

from pig.body.model import NUM_JOINTS, SMPLX_PARENTS, BodyModel
from pig.body.params import SmplxParams
from pig.data.dna import DnaCapture
from pig.data.raw import RawCamera
from pig.data.smc_writer import write_smc


class PhotoLikeCapture:
    """Two cameras of smooth images with mild noise (JPEG sizes near real photographs, unlike pure noise)."""

    def __init__(self, width: int, height: int, frames: int):
        rng = np.random.default_rng(0)
        self.source = Path("<bench>")
        self.frames = list(range(frames))
        self.params = SmplxParams(np.zeros((frames, NUM_JOINTS, 3)), np.zeros(10), np.zeros((frames, 10)),
                                  np.zeros((frames, 3)))
        K = np.array([[2000.0, 0, width / 2], [0, 2000.0, height / 2], [0, 0, 1]])
        self.cameras = {f"cam{i}": RawCamera(f"cam{i}", K, np.eye(3), np.array([0, 0, 3.0]), width, height)
                        for i in range(2)}
        low = cv2.resize(rng.integers(0, 256, (height // 64, width // 64, 3), dtype=np.uint8), (width, height),
                         interpolation=cv2.INTER_CUBIC)
        self.image = np.clip(low + rng.normal(0, 4, low.shape), 0, 255).astype(np.uint8)
        self.mask = np.zeros((height, width), np.uint8)
        cv2.ellipse(self.mask, (width // 2, height // 2), (width // 5, height // 3), 0, 0, 360, 255, -1)

    def has_frame(self, camera, frame):
        return True

    def read_image(self, camera, frame):
        return self.image

    def read_mask(self, camera, frame):
        return self.mask


def best_ms(fn, repeats: int) -> float:
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - start)
    return best * 1e3


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--width", type=int, default=2048)
    parser.add_argument("--height", type=int, default=2448)
    parser.add_argument("--frames", type=int, default=4)
    parser.add_argument("--repeats", type=int, default=7)
    args = parser.parse_args()
    cv2.setNumThreads(1)  # one decode per core, as the preprocess stage runs it
    arrays = {"v_template": np.zeros((3, 3)), "f": np.array([[0, 1, 2]]), "shapedirs": np.zeros((3, 3, 20)),
              "posedirs": np.zeros((3, 3, (NUM_JOINTS - 1) * 9)), "J_regressor": np.full((NUM_JOINTS, 3), 1 / 3),
              "weights": np.full((3, NUM_JOINTS), 1 / NUM_JOINTS), "kintree_table": np.stack([SMPLX_PARENTS, np.arange(NUM_JOINTS)])}
    with tempfile.TemporaryDirectory() as tmp:
        capture = PhotoLikeCapture(args.width, args.height, args.frames)
        start = time.perf_counter()
        main_path, annots_path = write_smc(capture, tmp, "0000_00", BodyModel(arrays), image_ext=".jpg", jpeg_quality=95)
        write_s = time.perf_counter() - start
        path = "Camera_5mp/0/color/1"
        with h5py.File(main_path, "r") as handle, h5py.File(annots_path, "r") as annots:
            data = handle[path][()]
            mask_data = annots["Mask/0/mask/1"][()]
        bgr = cv2.imdecode(data, cv2.IMREAD_COLOR)
        dna = DnaCapture(tmp, "0000_00")
        dna.read_image("0", 0)  # warm the handle and the key index

        def reopen_and_read():
            with h5py.File(main_path, "r") as handle:
                handle[path][()]

        def read_bytes():
            dna._file("main")[path][()]

        rows = [
            ("h5py read of the encoded bytes (file open)", best_ms(read_bytes, args.repeats)),
            ("h5py open + read + close per image", best_ms(reopen_and_read, args.repeats)),
            ("cv2.imdecode (JPEG -> BGR)", best_ms(lambda: cv2.imdecode(data, cv2.IMREAD_COLOR), args.repeats)),
            ("DnaCapture.read_image (bytes, decode, size check, RGB)", best_ms(lambda: dna.read_image("0", 1), args.repeats)),
            ("DnaCapture.read_mask (max over channels)", best_ms(lambda: dna.read_mask("0", 1), args.repeats)),
            ("  before: RGB by a reversed-view copy", best_ms(lambda: np.ascontiguousarray(bgr[..., ::-1]), args.repeats)),
            ("  now:    RGB by cv2.cvtColor", best_ms(lambda: cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB), args.repeats)),
            ("  before: mask IMREAD_COLOR + max(axis=2)",
             best_ms(lambda: cv2.imdecode(mask_data, cv2.IMREAD_COLOR).max(axis=2), args.repeats)),
        ]
        dna.close()
    print(f"frame {args.width}x{args.height} (WxH), JPEG q95 {data.size / 1e6:.2f} MB; "
          f"write_smc {2 * args.frames} images + masks: {write_s:.1f} s")
    print(f"{'step':58s} {'ms':>8s}")
    for name, ms in rows:
        print(f"{name:58s} {ms:8.2f}")
    decode, total = rows[2][1], rows[3][1]
    print(f"read_image / imdecode = {total / decode:.2f}; reopening per read adds "
          f"{(rows[1][1] - rows[0][1]) / total:.1%} of read_image; RGB conversion before/now = "
          f"{rows[5][1] / rows[6][1]:.0f}x; mask before/now = {rows[7][1] / rows[4][1]:.0f}x")


if __name__ == "__main__":
    main()

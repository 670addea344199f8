"""Lossless render storage codecs: bytes per view, encode and decode ms per view (one thread), exact round trip.

Views are a capture's masked ground-truth images (black background, as renders are), at their size and resized
to THuman4's 1330 x 1150 (smoother than a real render there: a lower bound on its bytes). Beside the store's codecs,
`png-level3` is the PNG setting the store used before (zlib level 3, libpng's adaptive row filters): the baseline of
the current one, timed in the same process.

    python benchmarks/render_codecs.py --capture results/synthetic/subject00/capture --views 6
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import cv2
import numpy as np

from pig.data.capture import Capture
from pig.data.images import decode_image
from pig.data.render_store import CODECS, encode_image


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--capture", type=Path, required=True, help="preprocessed capture")
    parser.add_argument("--split", default="novel_view")
    parser.add_argument("--views", type=int, default=6)
    args = parser.parse_args()
    capture = Capture.load(args.capture)
    views = capture.views(args.split)[: args.views]
    base = [np.round(capture.image(c, f) * capture.mask(c, f)[..., None] * 255).astype(np.uint8) for c, f in views]
    print(f"{'size':<10} {'codec':<10} {'KB/view':>8} {'encode ms':>10} {'decode ms':>10}")
    for images in (base, [cv2.resize(image, (1330, 1150), interpolation=cv2.INTER_LINEAR) for image in base]):
        for codec in [*CODECS, "png-level3"]:
            start = time.perf_counter()
            if codec == "png-level3":
                streams = [cv2.imencode(".png", np.ascontiguousarray(image[..., ::-1]),
                                        [cv2.IMWRITE_PNG_COMPRESSION, 3])[1].reshape(-1) for image in images]
            else:
                streams = [encode_image(image, codec) for image in images]
            middle = time.perf_counter()
            decoded = [decode_image(stream, codec.split("-")[0])[..., ::-1] for stream in streams]
            end = time.perf_counter()
            assert all(np.array_equal(d, image) for d, image in zip(decoded, images)), f"{codec} is not lossless"
            size = f"{images[0].shape[1]}x{images[0].shape[0]}"
            print(f"{size:<10} {codec:<10} {np.mean([s.size for s in streams]) / 1024:>8.1f} "
                  f"{1000 * (middle - start) / len(images):>10.1f} {1000 * (end - middle) / len(images):>10.1f}")


if __name__ == "__main__":
    main()

"""benchmarks/eval_scale.py's render breakdown: each part runs the render stage's own path on a fitted avatar."""
import sys
from pathlib import Path

import cv2
import numpy as np
import yaml

from pig.config import load_preset, load_section
from pig.data.render_store import RenderReader
from pig.render.api import RasterizerConfig
from pig.stages.evaluate import EvaluateConfig
from pig.stages.render import render_split

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from eval_scale import combined_rows, render_breakdown  # noqa: E402

SPLIT = "novel_view"  # 3 frames in the small capture (novel_pose has 1): a warm-up frame and two timed


def test_render_breakdown_rasterizes_and_encodes_what_the_stage_stores(tiny_fit, tmp_path):
    capture, checkpoint = tiny_fit
    preset = load_preset("test")
    preset.pop("_path")
    preset["evaluate"].update(device="cpu", render_codec="png", encode_workers=2)
    preset_path = tmp_path / "preset.yaml"
    preset_path.write_text(yaml.safe_dump(preset))
    renders = tmp_path / "renders" / SPLIT
    render_split(checkpoint, capture, SPLIT, renders, load_section(preset, "evaluate", EvaluateConfig),
                 load_section(preset, "rasterizer", RasterizerConfig))

    split = yaml.safe_load((capture / "split.json").read_text())[SPLIT]
    cameras, frames = split["cameras"], [int(f) for f in split["frames"]]
    assert len(frames) >= 3  # one warm-up frame and two timed ones
    rows, last = render_breakdown(capture, checkpoint, preset_path, SPLIT, 2, tmp_path)

    levels = sorted(int(p.name[3:]) for p in renders.glob("lod*"))
    assert len(levels) >= 2
    ms = {row["part"]: row["ms_per_view"] for row in rows if "ms_per_view" in row}
    per_lod = [name for lod in levels for name in
               (f"pose + decode avatar, lod{lod}", f"rasterize {len(cameras)} cameras, lod{lod}")]
    group_copy, each_copy = "to uint8 + copy to host, per group", "to uint8 + copy to host, per view (old)"
    per_view = [group_copy, each_copy, "encode png (1 thread)", "chunk write (2 frames)"]
    assert set(per_lod + per_view) <= set(ms)
    assert all(value > 0 for value in ms.values())
    for row in rows:  # a per-frame part's frame is all its cameras' views at that LOD
        if "ms_per_frame" in row and row["part"] in per_lod:
            np.testing.assert_allclose(row["ms_per_frame"], row["ms_per_view"] * len(cameras))
    # The stage's totals per view (averaged over the LODs) are the parts' sum: device and host (encode + write); the
    # baseline's copy of each view alone is not the stage's.
    device_parts = sum(ms[name] for name in per_lod) / len(levels) + ms[group_copy] \
        + ms.get("splat track to host", 0.0)
    np.testing.assert_allclose(ms["render stage per view: device"], device_parts, rtol=1e-9)
    np.testing.assert_allclose(ms["render stage per view: host, one thread"],
                               ms["encode png (1 thread)"] + ms["chunk write (2 frames)"], rtol=1e-9)
    bound = next(row["views_per_s"] for row in rows if "views_per_s" in row)
    np.testing.assert_allclose(bound, 1000 / max(device_parts, ms["render stage per view: host, one thread"] / 2))

    # The last timed frame's views, every LOD and camera: what the stage stored for them, and bytes that decode to it.
    frame = frames[2]
    assert set(last) == {(lod, cam) for lod in levels for cam in cameras}
    for (lod, cam), (image, stream) in last.items():
        stored = RenderReader(renders / f"lod{lod}").image_u8(cam, frame)
        assert image.dtype == np.uint8 and image.shape == stored.shape
        assert np.abs(image.astype(int) - stored.astype(int)).max() <= 1, (lod, cam)
        decoded = cv2.imdecode(np.frombuffer(stream.tobytes(), np.uint8), cv2.IMREAD_COLOR)[..., ::-1]
        np.testing.assert_array_equal(decoded, image)
    assert any(image.max() > 0 for image, _ in last.values())  # the avatar is in view, not a black frame
    # The stage's driver against the launched one: on the CPU the stage launches its frames, so the splats are equal.
    frame_ms = {row["part"]: row["ms_per_frame"] for row in rows if "ms_per_frame" in row}
    for lod in levels:
        assert frame_ms[f"{SPLIT} frame avatar, lod{lod}, stage"] > 0
        assert frame_ms[f"{SPLIT} frame avatar, lod{lod}, launched (old)"] > 0
    assert next(row["difference"] for row in rows if "difference" in row) == 0.0
    assert not list(tmp_path.glob(".render-breakdown-*"))  # the chunk writes' scratch folder is gone


def test_two_halves_combine_into_one_protocol_table():
    """--combine: per stage and split the views, seconds and bytes add up and the peaks are the larger; the first
    run's order is kept, and a stage only the second run has is kept too."""
    def row(stage, split, views, wall, rss, gpu, size):
        return {"stage": stage, "split": split, "views": views, "wall_s": wall, "peak_rss_mib": rss,
                "peak_gpu_mib": gpu, "bytes": size, "psnr": [30.0]}

    first = [row("render", "novel_view", 4000, 76.1, 4952, 768, 896), row("evaluate all", "novel_view", 4000, 49.9,
                                                                           5894, 30181, 2)]
    second = [row("evaluate all", "novel_view", 4000, 30.1, 6000, 30000, 3), row("render", "novel_view", 4000, 33.9,
                                                                                  4000, 900, 900),
              row("render", "novel_pose", 24000, 60.0, 4100, 2700, 5000)]
    merged = combined_rows([first, second])
    assert [(r["stage"], r["split"]) for r in merged] == [("render", "novel_view"), ("evaluate all", "novel_view"),
                                                          ("render", "novel_pose")]
    assert merged[0] == {"stage": "render", "split": "novel_view", "views": 8000, "wall_s": 110.0,
                         "peak_rss_mib": 4952, "peak_gpu_mib": 900, "bytes": 1796}
    assert (merged[1]["views"], merged[1]["wall_s"], merged[1]["peak_rss_mib"], merged[1]["bytes"]) == (8000, 80.0,
                                                                                                      6000, 5)
    assert merged[2]["views"] == 24000 and first[0]["views"] == 4000  # the inputs are left as they were

"""The evaluation end of the pipeline: EXR round trip, table layout from known summaries, and the whole
workflow through Snakemake on the tiny `test` preset (generate -> preprocess -> fit -> render -> evaluate -> tables)."""
from __future__ import annotations

import csv
import json
import math
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml

from pig.data.capture import Capture
from pig.data.capture_record import RECORD
from pig.data.exr import read_exr, write_exr
from pig.data.render_store import RenderReader, read_manifest
from pig.stages.tables import BLANK_ROW, make_tables

REPO = Path(__file__).resolve().parent.parent
# The test preset scores LPIPS with AlexNet; the tables name the backbone in the header.
# Snakemake through this interpreter, and its rules' `python` too: pytest may run from an unactivated environment.
ENV = {**os.environ, "PATH": os.pathsep.join([str(Path(sys.executable).parent), os.environ.get("PATH", "")])}
METRIC_COLUMNS = [f"{s}_{m}" for s in ("novel_view", "novel_pose") for m in ("psnr", "ssim", "lpips_alex", "fid")]


def test_exr_round_trip_is_exact(tmp_path, rng):
    alpha = rng.random((7, 5)).astype(np.float32)
    depth = (rng.random((7, 5)) * 50).astype(np.float32)
    write_exr(tmp_path / "a.exr", {"A": alpha, "Z": depth})
    back = read_exr(tmp_path / "a.exr")
    assert set(back) == {"A", "Z"}
    np.testing.assert_array_equal(back["A"], alpha)
    np.testing.assert_array_equal(back["Z"], depth)
    assert [p.name for p in tmp_path.iterdir()] == ["a.exr"]  # no temporary left behind
    with pytest.raises(ValueError, match="one shape"):
        write_exr(tmp_path / "b.exr", {"A": alpha, "Z": depth[:3]})


def _summary(root: Path, subject: str, variant: str, split: str, lod: int, psnr: float, **extra) -> Path:
    path = root / "synthetic" / subject / variant / "metrics" / f"{split}_lod{lod}.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    data = {"split": split, "lod": lod, "images": 4, "psnr": psnr, "ssim": 0.9, "lpips": math.nan, "fid": math.nan,
            "psnr_blank": 10.0, "ssim_blank": 0.5, "lpips_net": "alex", "lpips_note": "LPIPS weights missing",
            "fid_note": "FID is NaN: needs >= 2000 images per set, have 4", "splats": 100 * 2**lod,
            "model_mb": 1.0 + lod, "fps": 50.0 / (lod + 1), "device": "CPU x86_64, torch threads=2", **extra}
    path.write_text(json.dumps(data))
    return path


def test_tables_layout_and_means(tmp_path):
    summaries = []
    for variant, base in (("pig", 30.0), ("no_offsets", 25.0)):
        for s, subject in enumerate(("s0", "s1")):
            for split in ("novel_view", "novel_pose"):
                for lod in range(2):
                    psnr = base + s * 2 + lod + (0 if split == "novel_view" else -3)
                    summaries.append(_summary(tmp_path, subject, variant, split, lod, psnr))
    logs = []
    for subject in ("s0", "s1"):
        log = tmp_path / "synthetic" / subject / "pig" / "train_log.csv"
        pd.DataFrame({"iteration": [0, 10, 20], "wall_s": [0.0, 5.0, 9.0], "heldout_psnr": [12.0, np.nan, 20.0]}).to_csv(log, index=False)
        logs.append(log)
    out = tmp_path / "tables"
    make_tables("synthetic", summaries, logs, ["pig", "no_offsets"], out)

    main = pd.read_csv(out / "synthetic.csv")
    assert list(main["variant"]) == ["pig", "no_offsets", BLANK_ROW]
    assert set(METRIC_COLUMNS + ["splats"]) <= set(main.columns)
    pig = main.set_index("variant").loc["pig"]
    # Finest LOD (1), mean over subjects 0 and 2 dB apart: 30 + 1 + 1.
    assert pig["novel_view_psnr"] == pytest.approx(32.0)
    assert pig["novel_pose_psnr"] == pytest.approx(29.0)
    assert pig["splats"] == 200
    assert math.isnan(pig["novel_view_fid"]) and "2000 images" in pig["notes"]
    assert main.set_index("variant").loc[BLANK_ROW, "novel_view_psnr"] == pytest.approx(10.0)

    lod = pd.read_csv(out / "synthetic_lod.csv")
    assert list(lod["lod"]) == ["1/2", "2/2", "1/2", "2/2"]
    assert list(lod["splats"]) == [100, 200, 100, 200]
    assert lod["psnr"].tolist() == pytest.approx([31.0, 32.0, 26.0, 27.0])
    assert {"mb", "fps", "device"} <= set(lod.columns)
    markdown = (out / "synthetic.md").read_text()
    # Rounded as papers print, notes as footnotes marked on their rows.
    assert re.search(r"^\| pig[¹²³⁴⁵⁶⁷⁸⁹⁰˒]* \| 32\.00 \|", markdown, flags=re.M) and "n/a" in markdown
    assert re.search(r"^\d+\. FID is NaN: needs >= 2000 images", markdown, flags=re.M)
    assert (out / "synthetic_training.png").stat().st_size > 1000


def test_tables_reject_missing_variant(tmp_path):
    path = _summary(tmp_path, "s0", "pig", "novel_view", 0, 30.0)
    with pytest.raises(ValueError, match="no summaries for variant 'fixed_anchors'"):
        make_tables("synthetic", [path], [], ["fixed_anchors"], tmp_path / "tables")


@pytest.mark.slow
def test_workflow_end_to_end(tmp_path):
    """`snakemake` on the test preset from an empty working directory to its default target (the synthetic
    tables and the montages), then `snakemake --report`; the working directory and the preset's path hold
    spaces, which every rule's command must quote."""
    work = tmp_path / "work dir"
    work.mkdir()
    (work / "config").symlink_to(REPO / "config")
    # The test preset with a longer fit: its 40 iterations are sized for the fit tests, not for a
    # trained avatar; 200 take ~20 s on two quiet cores.
    preset = yaml.safe_load((REPO / "config" / "presets" / "test.yaml").read_text())
    preset["fit"].update(iterations=200, eval_every=100)
    (work / "pipeline preset.yaml").write_text(yaml.safe_dump(preset))
    command = [sys.executable, "-m", "snakemake", "--snakefile", str(REPO / "Snakefile"), "--directory", str(work),
               "--config", f"preset={work / 'pipeline preset.yaml'}"]
    done = subprocess.run([*command, "--cores", "2"], capture_output=True, text=True, timeout=600, env=ENV)
    logs = "\n".join(f"== {p}\n{p.read_text()[-2000:]}" for p in sorted(work.glob("results/**/logs/*.log")))
    assert done.returncode == 0, f"{done.stdout[-3000:]}\n{done.stderr[-5000:]}\n{logs}"

    tables = work / "results" / "tables"
    main = pd.read_csv(tables / "synthetic.csv").set_index("variant")
    assert {"pig", BLANK_ROW} <= set(main.index)
    assert set(METRIC_COLUMNS + ["splats", "notes"]) <= set(main.columns)
    for split in ("novel_view", "novel_pose"):
        # The fitted avatar must beat an all-black render by a wide margin on both held-out splits
        # (3 dB: less than half the black image's squared error).
        assert main.loc["pig", f"{split}_psnr"] > main.loc[BLANK_ROW, f"{split}_psnr"] + 3
        assert main.loc["pig", f"{split}_ssim"] > main.loc[BLANK_ROW, f"{split}_ssim"]
    lod = pd.read_csv(tables / "synthetic_lod.csv")
    assert {"lod", "splats", "psnr", "ssim", "lpips_alex", "fid", "mb", "fps", "device"} <= set(lod.columns)
    assert (lod["splats"].diff().dropna() > 0).all() and (lod["fps"] > 0).all()
    for name in ("synthetic.md", "synthetic_lod.md", "synthetic_training.png"):
        assert (tables / name).stat().st_size > 0
    # Renders: chunks holding every camera and frame of each split and LOD, no per-view PNG or EXR by default; the
    # manifest lists them and capture.json records the capture.
    renders = work / "results" / "synthetic" / "subject00" / "pig" / "renders"
    split_json = json.loads((work / "results" / "synthetic" / "subject00" / "capture" / "split.json").read_text())
    capture = Capture.load(work / "results" / "synthetic" / "subject00" / "capture")
    for split in ("novel_view", "novel_pose"):
        assert not list(renders.glob(f"{split}/lod0/*/*.png")) and not list(renders.glob(f"{split}/lod0/*/*.exr"))
        assert read_manifest(renders / split)["frames"] == [int(f) for f in split_json[split]["frames"]]
        assert json.loads((renders / split / RECORD).read_text())["fingerprint"] == capture.fingerprint()
        reader = RenderReader(renders / split / "lod0")
        assert all(reader.has(cam, int(frame)) for cam in split_json[split]["cameras"] for frame in split_json[split]["frames"])

    # The report: the workflow's description, the tables as HTML pages (their numbers rounded from the CSV), the
    # training plot, the fit's loss curve, a montage of each split and the turntable's page, each embedded.
    montages = [f"results/synthetic/subject00/pig/montage/{split}.png" for split in ("novel_view", "novel_pose")]
    for montage in montages:
        assert (work / montage).stat().st_size > 10_000
    done = subprocess.run([*command, "--report", "report.html"], capture_output=True, text=True, timeout=300, env=ENV)
    assert done.returncode == 0, done.stderr[-3000:]
    html = (work / "report.html").read_text()
    assert "PiG-Avatar: an animatable Gaussian-splat avatar from multi-view video" in html
    assert "compute preset <tt" in html and "dir/pipeline preset.yaml</tt>" in html
    with open(tables / "synthetic.csv") as table:
        pig_row = next(row for row in csv.DictReader(table) if row["variant"] == "pig")
    page = (tables / "synthetic.html").read_text()
    assert f">{float(pig_row['novel_view_psnr']):.2f}<" in page  # 2 decimals (ties aside: tests/test_table_format.py)
    assert "System Message" not in html  # docutils' notice of a broken caption
    pages = ["results/tables/synthetic.html", "results/tables/synthetic_lod.html", "results/tables/synthetic_regions.html",
             "results/synthetic/subject00/pig/animate/preview.html"]
    pictures = ["results/tables/synthetic_training.png", "results/synthetic/subject00/pig/train_log.png", *montages]
    for path in [*pages, *pictures]:
        assert html.count(f'"{path}"') >= 1, path
    assert html.count('"mime_type": "image/png"') == len(pictures)
    assert html.count('"mime_type": "text/html"') == len(pages)

"""Each layout end to end through the workflow at the `test` preset, in one Snakemake run: the synthetic subject
written as an EasyMocap sequence (frame folders, hand PCA fits), an ActorsHQ sequence nested as
Actor01/Sequence1/4x, and an AvatarReX subject with one video a camera; each a dataset of its own, built to its
table as `snakemake --cores 2 results/tables/mine.csv --configfile my.yaml` builds a user's."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pandas as pd
import torch
import yaml

from layout_writers import write_actorshq, write_avatarrex, write_easymocap
from pig.body.model import BodyModel
from pig.config import load_preset, load_section
from pig.data.capture import Capture
from pig.data.synthetic import SyntheticConfig, generate_capture
from pig.data.thuman4 import Thuman4Capture

REPO = Path(__file__).resolve().parent.parent
ENV = {**os.environ, "PATH": os.pathsep.join([str(Path(sys.executable).parent), os.environ.get("PATH", "")])}
SPLIT = {"novel_view_count": 1, "novel_pose_fraction": 0.25}


def test_each_layout_runs_to_its_table(tmp_path):
    preset = load_preset("test")
    preset.pop("_path")
    preset["fit"].update(iterations=20, eval_every=20)  # the layouts are under test here, not the fit
    cfg = load_section(preset, "synthetic", SyntheticConfig)
    cfg.cameras, cfg.frames, cfg.width, cfg.height = 4, 4, 48, 48
    cfg.distortion = 0.0  # ActorsHQ's frames are undistorted
    raw = generate_capture(tmp_path / "synthetic" / "subject00", cfg, progress=False)
    thuman = Thuman4Capture(raw)
    body_model = str(raw / "body_model.npz")
    model = BodyModel.from_file(body_model, dtype=torch.float64)
    data = tmp_path / "data"
    write_easymocap(thuman, data / "easymocap" / "seq1", model, components=6)
    write_actorshq(thuman, data / "actorshq" / "Actor01" / "Sequence1")
    write_avatarrex(thuman, data / "avatarrex" / "zzr", video=True)
    datasets = {
        "easymocap": {"subjects": ["seq1"], "reader": {"masks": "mask-schp"}},
        "actorshq": {"subjects": ["actor01"], "subject_paths": {"actor01": "Actor01/Sequence1"},
                     "reader": {"scale": "4x"}},
        "avatarrex": {"subjects": ["zzr"]},
    }
    work = tmp_path / "work"
    work.mkdir()
    (work / "config").symlink_to(REPO / "config")
    paths = {}
    for name, extra in datasets.items():
        path = tmp_path / f"{name}.yaml"
        path.write_text(yaml.safe_dump({"name": name, "format": name, "generated": False, "root": str(data / name),
                                        "body_model": body_model, "split": SPLIT, **extra}))
        paths[name] = str(path)
    (tmp_path / "preset.yaml").write_text(yaml.safe_dump(preset))
    (tmp_path / "my.yaml").write_text(yaml.safe_dump({"preset": str(tmp_path / "preset.yaml"), "datasets": paths,
                                                      "variants": ["pig"]}))
    targets = [f"results/tables/{name}.csv" for name in datasets]
    done = subprocess.run([sys.executable, "-m", "snakemake", *targets, "--snakefile", str(REPO / "Snakefile"),
                           "--directory", str(work), "--cores", "2", "--configfile", str(tmp_path / "my.yaml")],
                          capture_output=True, text=True, timeout=900, env=ENV)
    logs = "\n".join(f"== {p}\n{p.read_text()[-2000:]}" for p in sorted(work.glob("results/**/logs/*.log")))
    assert done.returncode == 0, f"{done.stdout[-3000:]}\n{done.stderr[-5000:]}\n{logs}"

    for name, extra in datasets.items():
        table = pd.read_csv(work / "results" / "tables" / f"{name}.csv").set_index("variant")
        assert table.loc["pig", "novel_view_psnr"] > 10, name
        capture = Capture.load(work / "results" / name / extra["subjects"][0] / "capture")
        assert len(capture.cameras) == len(thuman.cameras) and capture.frames == thuman.frames
        report = json.loads((work / "results" / name / extra["subjects"][0] / "capture" / "report.json").read_text())
        assert report["images"] == len(thuman.cameras) * len(thuman.frames) and report["missing"] == 0
        assert min(c["iou"] for c in report["projection_check"]["cameras"].values()) >= 0.9
    # Nothing was written into the raw captures.
    assert sorted(p.name for p in (data / "avatarrex" / "zzr").iterdir()) == sorted(
        ["calibration_full.json", "smpl_params.npz", *(f"{22010700 + i}" for i in range(len(thuman.cameras))),
         *(f"{22010700 + i}.mkv" for i in range(len(thuman.cameras)))])

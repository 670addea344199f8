"""The paper's evaluation protocol as configured (Section 4.1): subjects per table, and the camera and frame
counts the dataset YAMLs' splits give on camera/frame lists shaped like the real captures."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from pig.config import load_section, load_yaml
from pig.data.dna import required_files
from pig.data.splits import SplitConfig, make_split

REPO = Path(__file__).resolve().parent.parent
THUMAN4_CAMERAS = [f"cam{i:02d}" for i in range(24)]
DNA_CAMERAS = [str(i) for i in range(60)]  # Camera_5mp "0".."47", Camera_12mp "48".."59"


def _dataset(name: str) -> dict:
    return load_yaml(REPO / "config" / "datasets" / f"{name}.yaml")


def _split(name: str, cameras: list[str], frames: int, subject: str) -> dict:
    return make_split(cameras, list(range(frames)), load_section(_dataset(name), "split", SplitConfig), subject)


def _counts(split: dict) -> dict:
    return {part: (len(split[part]["cameras"]), len(split[part]["frames"])) for part in split}


def test_configured_subjects_are_the_papers():
    # As the workflow reads them (PyYAML): strings, not YAML 1.1 numbers.
    assert yaml.safe_load((REPO / "config" / "datasets" / "thuman4.yaml").read_text())["subjects"] == [
        "subject00", "subject01", "subject02"]
    dna = yaml.safe_load((REPO / "config" / "datasets" / "dna.yaml").read_text())
    # The paper names 0165, 0166, 0206 (main table), 0102 (ablation) and 0012 (noise).
    assert [s.split("_")[0] for s in dna["subjects"]] == ["0165", "0166", "0206"]
    assert dna["ablation_subjects"] == ["0102"] and dna["noise_subjects"] == ["0012"]
    assert all(isinstance(s, str) for key in ("subjects", "ablation_subjects", "noise_subjects") for s in dna[key])


# THuman4 frame counts per subject (FORMATS.md); the paper: 23 training cameras, 1 held out, train on the first
# 2000 timesteps, novel pose on the remaining 500 (on all 24 cameras).
@pytest.mark.parametrize("subject, frames", [("subject00", 2500), ("subject01", 5060), ("subject02", 3110)])
def test_thuman4_split_has_the_papers_counts(subject, frames):
    split = _split("thuman4", THUMAN4_CAMERAS, frames, subject)
    assert _counts(split) == {"train": (23, 2000), "novel_view": (1, 2000), "novel_pose": (24, 500)}
    assert split["train"]["cameras"] == THUMAN4_CAMERAS[:23] and split["novel_view"]["cameras"] == ["cam23"]
    assert split["train"]["frames"] == list(range(2000)) == split["novel_view"]["frames"]
    assert split["novel_pose"]["frames"] == list(range(2000, 2500))


# DNA-Rendering: 48 training cameras, 12 held out, the first 80% of the frames for training and the last 20%
# for novel pose. Part 1 sequences have 225 frames (180 + 45), some 150 (120 + 30).
@pytest.mark.parametrize("frames, train, tail", [(225, 180, 45), (150, 120, 30)])
@pytest.mark.parametrize("subject", ["0165_08", "0166_04", "0206_04", "0102", "0012"])
def test_dna_split_has_the_papers_counts(subject, frames, train, tail):
    split = _split("dna", DNA_CAMERAS, frames, subject)
    assert _counts(split) == {"train": (48, train), "novel_view": (12, train), "novel_pose": (60, tail)}
    assert split["train"]["cameras"] == DNA_CAMERAS[:48] and split["novel_view"]["cameras"] == DNA_CAMERAS[48:]
    assert split["train"]["frames"] == list(range(train)) and split["novel_pose"]["frames"] == list(range(train, frames))


def test_synthetic_split():
    cams = [f"cam{i:02d}" for i in range(12)]
    split = _split("synthetic", cams, 24, "subject00")
    assert split["novel_view"]["cameras"] == ["cam03", "cam09"]
    assert split["train"]["cameras"] == [c for c in cams if c not in ("cam03", "cam09")]
    assert split["train"]["frames"] == list(range(18)) and split["novel_pose"]["frames"] == list(range(18, 24))
    assert split["novel_pose"]["cameras"] == cams and split["novel_view"]["frames"] == split["train"]["frames"]


def test_dna_subject_without_suffix_is_a_folder_of_its_one_sequence(tmp_path):
    """`0102` (no suffix known): data/dna/0102/<seq>.smc with its annotations under data/dna/annotations/."""
    main = tmp_path / "0102" / "0102_02.smc"
    annots = tmp_path / "annotations" / "0102_02_annots.smc"
    for path in (main, annots):
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(b"")
    assert required_files(tmp_path / "0102") == [main, annots]


def _workflow_helpers(datasets: dict[str, Path]) -> dict:
    """The functions of workflow/rules/common.smk (plain Python) bound to a workflow config."""
    namespace = {"config": {"preset": "test", "datasets": {k: str(v) for k, v in datasets.items()}}}
    exec(compile((REPO / "workflow" / "rules" / "common.smk").read_text(), "common.smk", "exec"), namespace)
    return namespace


def test_subjects_accessor_keeps_each_tables_subjects_apart(tmp_path):
    datasets = {name: REPO / "config" / "datasets" / f"{name}.yaml" for name in ("thuman4", "dna")}
    subjects = _workflow_helpers(datasets)["subjects"]
    assert subjects("dna") == ["0165_08", "0166_04", "0206_04"]
    assert subjects("dna", "ablation") == ["0102"] and subjects("dna", "noise") == ["0012"]
    assert subjects("thuman4") == ["subject00", "subject01", "subject02"] and subjects("thuman4", "ablation") == []

    # The workflow reads dataset YAML as the stages do (pig.config.load_yaml): unquoted ids stay strings,
    # where plain YAML 1.1 would read 0012 as the octal 10 and 0166_04 as 7556.
    unquoted = tmp_path / "dna.yaml"
    unquoted.write_text("subjects: [0166_04]\nnoise_subjects: [0012]\nablation_subjects: [12]\n")
    subjects = _workflow_helpers({"dna": unquoted})["subjects"]
    assert subjects("dna") == ["0166_04"] and subjects("dna", "noise") == ["0012"]
    with pytest.raises(ValueError, match=r"dna\.yaml: `ablation_subjects` must be a non-empty list of subject names, "
                                         r"found \[12\]"):
        subjects("dna", "ablation")


@pytest.mark.slow
def test_main_dna_table_plans_only_the_three_subjects(tmp_path):
    """`snakemake -n results/tables/dna.csv` plans jobs for the main subjects only, with every sequence present."""
    (tmp_path / "config").symlink_to(REPO / "config")
    dataset = _dataset("dna")
    for seq in dataset["subjects"] + dataset["ablation_subjects"] + dataset["noise_subjects"]:
        for path in (tmp_path / "data" / "dna" / f"{seq}.smc", tmp_path / "data" / "dna" / "annotations" / f"{seq}_annots.smc"):
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_bytes(b"")  # a plan only checks that the inputs exist
    (tmp_path / "SMPLX_NEUTRAL.npz").write_bytes(b"")
    (tmp_path / "dna.yaml").write_text(yaml.safe_dump({**dataset, "body_model": str(tmp_path / "SMPLX_NEUTRAL.npz")}))
    (tmp_path / "run.yaml").write_text(yaml.safe_dump({"preset": "test", "datasets": {"dna": str(tmp_path / "dna.yaml")}}))
    done = subprocess.run([sys.executable, "-m", "snakemake", "-n", "results/tables/dna.csv", "--snakefile", str(REPO / "Snakefile"),
                           "--directory", str(tmp_path), "--configfile", str(tmp_path / "run.yaml")],
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    planned = {word.split("/")[2] for word in done.stdout.replace(",", " ").split() if word.startswith("results/dna/")}
    assert planned == {"0165_08", "0166_04", "0206_04"}, done.stdout[-3000:]

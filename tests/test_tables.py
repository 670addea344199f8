"""The tables stage's ablation, noise, regions and LOD tables and its training plot, from hand-written summaries,
and the workflow targets that build them for whichever variants the config names."""
from __future__ import annotations

import json
import math
import re
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml

from pig.avatar.variants import table_variants, variant_kind
from pig.config import ConfigError, load_preset
from pig.stages import tables
from pig._cli import run_cli
from pig.stages.tables import BLANK_ROW, REGION_KEYS, SPLITS, make_table, make_tables, noise_sigmas

REPO = Path(__file__).resolve().parent.parent
SUBJECTS = ("s0", "s1")


def _value(key: str, variant: str, subject: str, split: str, lod: int) -> float:
    """A distinct value per key and run, so that a mean over the wrong rows shows."""
    seed = sum(map(ord, f"{key}/{variant}/{subject}/{split}")) + 7 * lod
    return float(np.random.default_rng(seed).uniform(1, 40))


def _summary(root: Path, subject: str, variant: str, split: str, lod: int, regions: bool = True, **extra) -> Path:
    path = root / "synthetic" / subject / variant / "metrics" / f"{split}_lod{lod}.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    data = {"split": split, "lod": lod, "images": 4, "lpips_net": "alex", "fid": math.nan, "splats": 100 * 2 ** lod,
            "model_mb": 1.0 + lod, "fps": 50.0 / (lod + 1), "device": "cpu", "psnr_blank": 10.0, "ssim_blank": 0.5}
    data.update({key: _value(key, variant, subject, split, lod) for key in ("psnr", "ssim", "lpips")})
    if regions:
        data.update({key: _value(key, variant, subject, split, lod) for key in REGION_KEYS})
    data.update(extra)
    path.write_text(json.dumps(data))
    # The evaluate stage's record of the split's pass (the workflow's output of its job), listing the LODs so far.
    record = path.parent / f"{split}.json"
    levels = sorted({lod, *(json.loads(record.read_text())["levels"] if record.is_file() else [])})
    record.write_text(json.dumps({"split": split, "levels": levels,
                                  "summaries": [f"{split}_lod{level}.json" for level in levels]}))
    return path


def _summaries(root: Path, levels: dict[str, int], regions: bool = True) -> list[Path]:
    """Summaries of every subject, split and level of `levels` {variant: number of levels}."""
    return [_summary(root, subject, variant, split, lod, regions)
            for variant, count in levels.items() for subject in SUBJECTS for split in SPLITS for lod in range(count)]


def _expected(paths: list[Path], variant: str, split: str, key: str) -> float:
    """Mean of `key` over the subjects' summaries of `variant` and `split` at the variant's finest level, read back."""
    records = [json.loads(p.read_text()) for p in paths if p.parts[-3] == variant]
    finest = max(r["lod"] for r in records)
    return float(np.mean([r[key] for r in records if r["split"] == split and r["lod"] == finest]))


# ---- which variants a table takes ----


def test_each_table_takes_its_kind_of_variant_from_any_subset():
    preset = load_preset("test")
    assert [variant_kind(preset, v) for v in ("pig", "template_bound", "local_offsets", "noise_0.2", "lod_1of1")] == [
        "structural", "structural", "structural", "noise", "lod"]
    names = ["noise_0.25", "pig", "template_bound", "lod_1of1", "no_precond"]
    assert table_variants(preset, names, "main") == names == table_variants(preset, names, "regions")
    assert table_variants(preset, names, "ablation") == ["pig", "template_bound", "no_precond"]
    assert table_variants(preset, names, "noise") == ["noise_0.25", "pig"]
    assert table_variants(preset, ["template_bound"], "noise") == []
    with pytest.raises(ConfigError, match=r"unknown variant 'nope'"):
        table_variants(preset, ["pig", "nope"], "ablation")
    with pytest.raises(ConfigError, match=r"unknown table 'lod'; expected main, ablation, noise or regions"):
        table_variants(preset, names, "lod")


# ---- the tables' contents ----


def test_ablation_table_of_a_subset_of_variants_with_region_columns(tmp_path):
    paths = _summaries(tmp_path, {"pig": 2, "template_bound": 2, "no_offsets": 2})
    out = tmp_path / "tables"
    make_table("ablation", "synthetic", paths, ["template_bound", "pig"], out)  # no_offsets fitted, not asked
    table = pd.read_csv(out / "synthetic_ablation.csv").set_index("variant")
    assert list(table.index) == ["template_bound", "pig", BLANK_ROW]
    for variant in ("template_bound", "pig"):
        for split in SPLITS:
            for key in ("psnr", "ssim", *REGION_KEYS):
                assert table.loc[variant, f"{split}_{key}"] == pytest.approx(_expected(paths, variant, split, key), rel=1e-5)
            assert table.loc[variant, f"{split}_lpips_alex"] == pytest.approx(_expected(paths, variant, split, "lpips"), rel=1e-5)
    assert table.loc[BLANK_ROW, "novel_view_psnr"] == 10.0 and math.isnan(table.loc[BLANK_ROW, "novel_view_psnr_garment"])
    markdown = (out / "synthetic_ablation.md").read_text()
    assert markdown.startswith("## synthetic: structural ablation") and "| template_bound |" in markdown
    assert "Novel poses drift (mm)↓ (last)" in markdown and "no_offsets" not in markdown


def test_real_captures_give_no_region_columns_and_no_regions_table(tmp_path):
    paths = _summaries(tmp_path, {"pig": 2, "no_precond": 2}, regions=False)
    out = tmp_path / "tables"
    make_tables("synthetic", paths, [], ["pig", "no_precond"], out)
    make_table("ablation", "synthetic", paths, ["pig", "no_precond"], out)
    for name in ("synthetic.csv", "synthetic_ablation.csv"):
        columns = pd.read_csv(out / name).columns
        assert not [c for c in columns if any(c.endswith(key) for key in REGION_KEYS)], name
        assert {"novel_view_psnr", "novel_pose_ssim", "splats"} <= set(columns)
    before = sorted(p.name for p in out.iterdir())
    with pytest.raises(ValueError, match=r"^no summary holds the ground-truth region metrics \(psnr_garment, .*drift_mm_last\): "
                                         r"only captures with ground truth \(a generated dataset such as synthetic\) have them$"):
        make_table("regions", "synthetic", paths, ["pig"], out)
    assert sorted(p.name for p in out.iterdir()) == before


def test_region_metrics_in_some_summaries_only_are_refused_by_name(tmp_path):
    paths = _summaries(tmp_path, {"pig": 1, "template_bound": 1})
    stale = _summary(tmp_path, "s1", "template_bound", "novel_pose", 0, regions=False)
    lacks = (rf"^{re.escape(str(stale))}: summary lacks the ground-truth region metrics \(psnr_garment, .*\) that "
             r".*/metrics/novel_view_lod0\.json has: written by an older evaluate stage")
    with pytest.raises(ValueError, match=lacks):
        make_table("regions", "synthetic", paths, ["pig", "template_bound"], tmp_path / "tables")
    partial = _summary(tmp_path, "s1", "template_bound", "novel_pose", 0)  # all keys, then drop two
    data = json.loads(partial.read_text())
    del data["drift_mm"], data["accuracy_mm_body"]
    partial.write_text(json.dumps(data))
    with pytest.raises(ValueError, match=rf"^{re.escape(str(partial))}: summary has only some ground-truth region metrics, lacks "
                                         r"\['accuracy_mm_body', 'drift_mm'\]; re-run evaluate$"):
        make_tables("synthetic", paths, [], ["pig", "template_bound"], tmp_path / "tables")
    assert not (tmp_path / "tables").exists()


def test_regions_table_per_variant_and_split(tmp_path):
    paths = _summaries(tmp_path, {"pig": 2, "template_bound": 2, "lod_1of1": 1})
    out = tmp_path / "tables"
    make_table("regions", "synthetic", paths, ["pig", "lod_1of1", "template_bound"], out)
    table = pd.read_csv(out / "synthetic_regions.csv")
    assert list(table.columns) == ["variant", "split", *REGION_KEYS]
    assert list(zip(table["variant"], table["split"])) == [(v, s) for v in ("pig", "lod_1of1", "template_bound") for s in SPLITS]
    for row in table.itertuples(index=False):
        for key in REGION_KEYS:
            assert getattr(row, key) == pytest.approx(_expected(paths, row.variant, row.split, key), rel=1e-5)
    assert "| template_bound | novel_pose |" in (out / "synthetic_regions.md").read_text()
    with pytest.raises(ValueError, match=r"no summaries for variant 'local_offsets'"):
        make_table("regions", "synthetic", paths, ["pig", "local_offsets"], out)


def test_noise_table_takes_sigma_from_the_preset_and_sorts_by_it(tmp_path):
    paths = _summaries(tmp_path, {"noise_0.25": 1, "pig": 1, "noise_0.1": 1}, regions=False)
    variants = ["noise_0.25", "pig", "noise_0.1"]
    preset = load_preset("test")
    sigmas = noise_sigmas("test", variants)
    assert sigmas == {v: preset["variants"].get(v, {}).get("fit", {}).get("sigma_body", 0.0) for v in variants}
    out = tmp_path / "tables"
    assert run_cli(tables.main, ["--table", "noise", "--dataset", "synthetic", "--summaries", *map(str, paths),
                                 "--variants", *variants, "--preset", "test", "--output", str(out)]) == 0
    table = pd.read_csv(out / "synthetic_noise.csv")
    assert list(table["variant"]) == sorted(variants, key=sigmas.get) and BLANK_ROW not in set(table["variant"])
    assert list(table.columns[:3]) == ["variant", "sigma_body", "sigma_body_deg"]
    for row in table.itertuples(index=False):
        assert row.sigma_body == sigmas[row.variant] and row.sigma_body_deg == pytest.approx(sigmas[row.variant] * 180 / math.pi, rel=1e-5)
        assert row.novel_view_psnr == pytest.approx(_expected(paths, row.variant, "novel_view", "psnr"), rel=1e-5)
    assert "| noise_0.25 | 0.250 | 14.3 |" in (out / "synthetic_noise.md").read_text()


def test_lod_table_has_the_single_level_variant_as_its_1of1_row(tmp_path):
    paths = _summaries(tmp_path, {"pig": 2, "lod_1of1": 1})
    paths = [p for p in paths if "novel_view" in p.name] + [p for p in paths if "novel_pose" in p.name]
    out = tmp_path / "tables"
    make_tables("synthetic", paths, [], ["pig", "lod_1of1"], out)
    lod = pd.read_csv(out / "synthetic_lod.csv")
    assert list(zip(lod["variant"], lod["lod"], lod["splats"])) == [("pig", "1/2", 100), ("pig", "2/2", 200), ("lod_1of1", "1/1", 100)]
    records = [json.loads(p.read_text()) | {"variant": p.parts[-3]} for p in paths]
    for row in lod.itertuples(index=False):
        level = int(row.lod.split("/")[0]) - 1
        same = [r for r in records if r["variant"] == row.variant and r["lod"] == level and r["split"] == "novel_view"]
        assert row.psnr == pytest.approx(np.mean([r["psnr"] for r in same]), rel=1e-5)


def test_training_plot_draws_every_variant_and_subject(tmp_path, monkeypatch):
    variants = ["pig", "template_bound", "noise_0.1", "lod_1of1"]
    paths = _summaries(tmp_path, {v: 1 for v in variants}, regions=False)
    logs = {}
    for v, variant in enumerate(variants):
        for s, subject in enumerate(SUBJECTS):
            log = tmp_path / "synthetic" / subject / variant / "train_log.csv"
            frame = pd.DataFrame({"iteration": [0, 10, 20, 30], "wall_s": [0.0, 4.0 + v, 9.0 + v, 12.0 + s],
                                  "heldout_psnr": [10.0 + v, np.nan, 20.0 + s, 22.0 + v + s]})
            if v % 2:  # logs with train_s (evaluations left out) plot it; older logs without it plot wall_s
                frame.insert(2, "train_s", frame["wall_s"] - [0.0, 1.0, 2.0, 3.0])
            frame.to_csv(log, index=False)
            logs[f"{variant} ({subject})"] = frame.dropna()
    drawn = {}

    def capture(path, figure, dpi=None):
        drawn.update({line.get_label(): (list(line.get_xdata()), list(line.get_ydata()), line.get_color(), line.get_linestyle())
                      for line in figure.axes[0].get_lines()})

    monkeypatch.setattr(tables, "write_figure", capture)
    make_tables("synthetic", paths, [p.parent.parent / "train_log.csv" for p in paths if p.name == "novel_view_lod0.json"],
                variants, tmp_path / "tables")
    assert set(drawn) == set(logs)
    for label, frame in logs.items():
        time = frame["train_s"] if "train_s" in frame else frame["wall_s"]
        assert drawn[label][:2] == (time.tolist(), frame["heldout_psnr"].tolist())
    # A colour per variant, a line style per subject.
    assert len({drawn[f"{v} (s0)"][2] for v in variants}) == len(variants)
    assert all(drawn[f"{v} (s0)"][2] == drawn[f"{v} (s1)"][2] for v in variants)
    assert drawn["pig (s0)"][3] != drawn["pig (s1)"][3]


def test_cli_refuses_train_logs_outside_the_main_table(tmp_path, capsys):
    path = _summary(tmp_path, "s0", "pig", "novel_view", 0)
    with pytest.raises(SystemExit) as exit_info:
        tables.main(["--table", "ablation", "--dataset", "synthetic", "--summaries", str(path), "--train-logs", str(path),
                     "--variants", "pig", "--output", str(tmp_path / "tables")])
    assert exit_info.value.code == 2
    assert "--train-logs: only the main table plots training, not --table ablation" in capsys.readouterr().err


# ---- the workflow's targets ----


def _synthetic_workdir(tmp_path: Path) -> Path:
    work = tmp_path / "work dir"
    work.mkdir()
    shutil.copytree(REPO / "config", work / "config")
    shutil.copyfile(REPO / "config" / "presets" / "test.yaml", work / "config" / "test preset.yaml")
    return work


@pytest.fixture(scope="module")
def snakemake_run():
    from test_workflow import snakemake_run

    return snakemake_run


def test_table_targets_schedule_just_the_variants_of_their_table(tmp_path, snakemake_run):
    from test_workflow import job_counts

    work = _synthetic_workdir(tmp_path)
    settings = ["--config", "preset=config/test preset.yaml", "variants=[pig,template_bound,noise_0.1,lod_1of1]"]
    # test preset: 2 levels, lod_1of1 1; 2 splits; one subject.
    expected = {"ablation": ["pig", "template_bound"], "noise": ["pig", "noise_0.1"],
                "regions": ["pig", "template_bound", "noise_0.1", "lod_1of1"]}
    for table, variants in expected.items():
        output = snakemake_run(work, f"results/tables/synthetic_{table}.csv", "--dry-run", "--printshellcmds", *settings)
        assert job_counts(output) == {"generate_capture": 1, "preprocess_capture": 1, "fit_avatar": len(variants),
                                      "render_split": 2 * len(variants), "evaluate": 2 * len(variants), "make_table": 1}
        command = next(line for line in output.splitlines() if "python -m pig tables " in line)
        # One evaluate job per split scores all of a variant's LODs; the table reads each LOD's summary.
        summaries = set(re.findall(r"results/synthetic/subject00/([^/ ]+)/metrics/(\S+\.json)", command))
        assert summaries == {(v, f"{split}_lod{lod}.json") for v in variants for split in ("novel_view", "novel_pose")
                             for lod in range(1 if v == "lod_1of1" else 2)}
        assert f"--table {table} " in command and f"--variants {' '.join(variants)} " in command
        assert "--preset 'config/test preset.yaml'" in command
    output = snakemake_run(work, "results/tables/synthetic.csv", "--dry-run", "--quiet", "rules", *settings)
    assert job_counts(output)["make_tables"] == 1 and job_counts(output)["fit_avatar"] == 4


def _failing_snakemake(workdir: Path, *args: str) -> str:
    """Output of a `snakemake ARGS` that must fail (run as test_workflow runs it)."""
    from test_workflow import snakemake_exit

    code, output = snakemake_exit(workdir, *args)
    assert code not in (0, None), output[-3000:]
    return output


@pytest.mark.parametrize("target, message", [
    ("thuman4_regions.csv", "results/tables/thuman4_regions.csv: region metrics need the ground-truth meshes that only "
                            "generated datasets have"),
    ("thuman4_ablation.csv", "results/tables/thuman4_ablation.csv: config/datasets/thuman4.yaml names no `ablation_subjects`"),
    ("synthetic_noise.csv", "results/tables/synthetic_noise.csv: none of the variants ['template_bound'] belongs to the "
                            "noise table"),
])
def test_table_targets_without_runs_are_refused_at_once(tmp_path, target, message):
    work = _synthetic_workdir(tmp_path)
    output = _failing_snakemake(work, f"results/tables/{target}", "--dry-run", "--config",
                                "preset=config/test preset.yaml", "variants=[template_bound]")
    assert message in output, output[-3000:]


def test_regions_target_builds_the_table_from_the_evaluate_summaries(tmp_path, snakemake_run):
    """A real run of make_table on summaries in place (the other rules left out)."""
    work = _synthetic_workdir(tmp_path)
    paths = [_summary(work / "results", "subject00", variant, split, lod)
             for variant in ("pig", "template_bound") for split in SPLITS for lod in range(2)]
    snakemake_run(work, "results/tables/synthetic_regions.csv", "--cores", "1", "--allowed-rules", "make_table",
                  "--config", "preset=config/test preset.yaml", "variants=[pig,template_bound]")
    table = pd.read_csv(work / "results" / "tables" / "synthetic_regions.csv")
    assert list(table["variant"]) == ["pig", "pig", "template_bound", "template_bound"]
    for row in table.itertuples(index=False):
        assert row.psnr_garment == pytest.approx(_expected(paths, row.variant, row.split, "psnr_garment"), rel=1e-5)
    assert yaml.safe_load((work / "config" / "datasets" / "synthetic.yaml").read_text())["generated"] is True

"""benchmarks/equal_time.py: a fit read from its train log and printed lines agrees with the same fit's JSON."""
import copy
import csv
import json
import math
import sys
from pathlib import Path

import pytest
import yaml

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from equal_time import (LEVER_MARKERS, SUMMARY_KEYS, averaged_pairs, averaged_table, fit_from_json,  # noqa: E402
                        fit_from_log, load_fits, plot_styles, printed_metrics, rule_table, table, wobble)

RUNS = Path(__file__).resolve().parents[1] / "benchmarks" / "gpu_runs"
# run27's no_precond came back whole: its JSON is the reference for what the printed lines and log give.
ENTRY = {"seed": 0, "budget_s": 900, "replicate": 1, "hold": "run27", "device": "H200"}
JSON_ENTRY = {**ENTRY, "json": "run27/no_precond.json", "log": "run27/no_precond_train_log.csv"}
LOG_ENTRY = {**ENTRY, "log": "run27/no_precond_train_log.csv", "text": "run27/no_precond.txt", "variant": "no_precond"}


def test_log_and_printed_lines_give_the_json_figures():
    whole, printed = fit_from_json(RUNS, JSON_ENTRY), fit_from_log(RUNS, LOG_ENTRY)
    assert printed["iterations"] == whole["iterations"]
    assert printed["train_s"] == pytest.approx(whole["train_s"], abs=1e-3)
    assert printed["curve"] == pytest.approx(whole["curve"])
    for split in ("novel_view", "novel_pose"):
        for key in SUMMARY_KEYS:
            decimals = 4 if key == "ssim" else 1 if "mm" in key else 2  # as the evaluate stage prints them
            assert printed["final"][split][key] == pytest.approx(whole["final"][split][key], abs=0.51 * 10**-decimals), key


def test_the_finest_printed_level_counts_and_a_missing_split_is_nan():
    text = "\n".join([
        "[evaluate] novel_view lod0: PSNR 20.00 SSIM 0.5000 (blank 1.00 / 0.1000) FID nan over 4 images",
        "[evaluate] novel_view lod2: PSNR 30.25 SSIM 0.9500 (blank 1.00 / 0.1000) FID nan over 4 images",
        "[evaluate] novel_view lod2: PSNR garment 21.50 body 28.00 background 35.00; accuracy garment 6.5 body 4.0 mm, "
        "completeness garment 4.5 body 9.0 mm, drift 11.0 mm (last frame 13.0)",
        "[evaluate] novel_pose lod3: LPIPS is NaN",  # a note, no figures
    ])
    final = printed_metrics(text)
    assert final["novel_view"]["psnr"] == 30.25 and final["novel_view"]["ssim"] == 0.95
    assert final["novel_view"]["accuracy_mm_body"] == 4.0 and final["novel_view"]["completeness_mm_garment"] == 4.5
    assert all(math.isnan(v) for v in final["novel_pose"].values())


def test_a_missing_split_prints_a_dash():
    fit = fit_from_log(RUNS, LOG_ENTRY)
    fit["final"]["novel_pose"] = dict.fromkeys(SUMMARY_KEYS, math.nan)
    row = [line for line in table([fit]).splitlines() if "| no_precond |" in line][0]
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert cells[5] == f"{fit['final']['novel_view']['psnr']:.2f}" and cells[7] == "-" and cells[8] == "-"


def test_replicates_average_the_splits_that_came_back_and_say_how_many():
    whole = fit_from_log(RUNS, LOG_ENTRY)
    cut_short = copy.deepcopy(whole)
    cut_short["replicate"] = 2
    cut_short["final"]["novel_pose"] = dict.fromkeys(SUMMARY_KEYS, math.nan)
    cut_short["final"]["novel_view"]["psnr"] = whole["final"]["novel_view"]["psnr"] - 1.0
    row = [line for line in table([whole, cut_short]).splitlines() if "| no_precond |" in line][0]
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert cells[5] == f"{whole['final']['novel_view']['psnr'] - 0.5:.2f} ± 0.50"
    assert cells[7] == f"{whole['final']['novel_pose']['psnr']:.2f} (1 of 2)"


def test_wobble_reads_the_late_curve_and_measures_each_dip_against_its_neighbours():
    # From 40 % of 10 s on: 30, 32, 30, 32 (mean 31, sd 1); the inner dips +2 and -2.
    assert wobble([(0.0, 20.0), (4.0, 30.0), (6.0, 32.0), (8.0, 30.0), (10.0, 32.0)]) == (4, 31.0, 1.0, 2.0)
    count, mean, sd, dip = wobble([(0.0, 20.0), (9.0, 30.0), (10.0, 31.0)])
    assert count == 2 and all(math.isnan(v) for v in (mean, sd, dip))


AVERAGED = {"json": "run30/pig_3.json", "log": "run30/pig_3_train_log.csv", "seed": 0, "budget_s": 300, "replicate": 1,
            "hold": "run30", "device": "H200", "label": "pig average 0.99", "overrides": "fit.average_decay=0.99"}
PLAIN = {**AVERAGED, "json": "run30/pig_0.json", "log": "run30/pig_0_train_log.csv"}
del PLAIN["label"], PLAIN["overrides"]


def test_a_labelled_fit_is_its_own_row_beside_its_variant(tmp_path):
    manifest = tmp_path / "equal_time.yaml"
    manifest.write_text(yaml.safe_dump({"fits": [PLAIN, AVERAGED]}))
    (tmp_path / "run30").symlink_to(RUNS / "run30")
    fits = load_fits(manifest)
    assert [f["variant"] for f in fits] == ["pig", "pig average 0.99"]
    first = table(fits).split("\n\n")[0]  # the per-variant table; the curve and wobble tables list each fit anyway
    rows = [line for line in first.splitlines() if line.startswith("| 0 | 5 min | pig")]
    assert [row.split(" | ")[2:4] for row in rows] == [["pig", "1"], ["pig average 0.99", "1"]]


def test_the_average_is_paired_with_its_iterate_at_the_same_evaluations():
    with open(RUNS / AVERAGED["log"], newline="") as file:
        logged = [r for r in csv.DictReader(file) if r["heldout_psnr_iterate"]]
    pairs = averaged_pairs(RUNS, AVERAGED)
    assert [t for t, _, _ in pairs] == [float(r["train_s"]) for r in logged] and len(pairs) >= 3
    gains = [float(r["heldout_psnr"]) - float(r["heldout_psnr_iterate"]) for r in logged]
    [row] = [line for line in averaged_table(RUNS, [{**AVERAGED, "variant": AVERAGED["label"]}]).splitlines()
             if line.startswith("| 0 |")]
    assert row.rstrip(" |").endswith(f"{sum(gains) / len(gains):+.2f} ({min(gains):+.2f} to {max(gains):+.2f})")
    assert averaged_table(RUNS, [{**PLAIN, "variant": "pig"}]) == ""  # no average, no table


def test_an_evaluated_last_iterate_is_a_replicate_of_the_plain_variant(tmp_path):
    # fit_gpu.py --evaluate-iterate's record (budget_iterate beside budget), built from run30's averaged pig with
    # other figures for the iterate: with `iterate_replicate` the manifest gives the averaged row and a plain `pig`
    # row pooled with run30's plain pig, whose curve is the logged iterate's (the average's before it started).
    record = json.loads((RUNS / AVERAGED["json"]).read_text())
    [result] = [r for r in record["results"] if r.get("budget")]
    result["budget_iterate"] = copy.deepcopy(result["budget"])
    for split in ("novel_view", "novel_pose"):
        for summary in result["budget_iterate"][split].values():
            summary["psnr"] -= 0.5
    (tmp_path / "run30").mkdir()
    (tmp_path / "run30" / "pig_3.json").write_text(json.dumps(record))
    for name in ("pig_3_train_log.csv", "pig_0.json", "pig_0_train_log.csv"):
        (tmp_path / "run30" / name).symlink_to(RUNS / "run30" / name)
    manifest = tmp_path / "equal_time.yaml"
    manifest.write_text(yaml.safe_dump({"fits": [PLAIN, {**AVERAGED, "iterate_replicate": 2}]}))
    fits = load_fits(manifest)
    assert [(f["variant"], f["replicate"]) for f in fits] == [("pig", 1), ("pig average 0.99", 1), ("pig", 2)]
    averaged, iterate = fits[1], fits[2]
    assert iterate["final"]["novel_view"]["psnr"] == pytest.approx(averaged["final"]["novel_view"]["psnr"] - 0.5)
    with open(RUNS / AVERAGED["log"], newline="") as file:
        logged = [r for r in csv.DictReader(file) if r["heldout_psnr"]]
    assert [p for _, p in iterate["curve"]] == [float(r["heldout_psnr_iterate"] or r["heldout_psnr"]) for r in logged]
    assert iterate["curve"][0] == averaged["curve"][0] and iterate["curve"][-1] != averaged["curve"][-1]
    [row] = [line for line in table(fits).split("\n\n")[0].splitlines() if line.startswith("| 0 | 5 min | pig |")]
    plain_nv = fit_from_json(RUNS, PLAIN)["final"]["novel_view"]["psnr"]
    nv = [plain_nv, iterate["final"]["novel_view"]["psnr"]]
    assert row.split(" | ")[3] == "2" and row.split(" | ")[5].startswith(f"{sum(nv) / 2:.2f} ± {(max(nv) - min(nv)) / 2:.2f}")
    assert len([line for line in averaged_table(tmp_path, fits).splitlines() if line.startswith("| 0 |")]) == 1


def _final(variant: str, seed: int, budget_s: int, view: float, pose: float = math.nan) -> dict:
    return {"variant": variant, "seed": seed, "budget_s": budget_s,
            "final": {"novel_view": {"psnr": view}, "novel_pose": {"psnr": pose}}}


def test_the_rule_compares_with_the_larger_seed0_five_minute_spread():
    fits = [_final("pig", 0, 300, v, p) for v, p in ((30.0, 28.0), (31.0, 28.1), (30.5, 28.05))]  # NV range 1.0
    fits += [_final("no_precond", 0, 300, v, p) for v, p in ((30.2, 27.0), (30.4, 27.3), (30.3, 27.2))]  # NP 0.3
    fits += [_final("pig", 1, 900, 32.0, 27.0), _final("no_precond", 1, 900, 30.5, 26.9),  # +1.5 NV beyond 1.0
             _final("pig", 0, 900, 31.0), _final("no_precond", 0, 900, 30.1),  # +0.9: within; no pose fits
             _final("template_bound", 1, 900, 20.0)]  # not compared
    rows = {tuple(c.strip() for c in line.strip("|").split("|")[1:4]): line
            for line in rule_table(fits).splitlines() if line.startswith("| - |")}
    assert "novel view 1.000 dB, novel pose 0.300 dB" in rule_table(fits)
    assert rows[("1", "15 min", "novel_view")].endswith("| +1.500 | pig beyond |")
    assert rows[("1", "15 min", "novel_pose")].endswith("| +0.100 | within the spread |")
    assert rows[("0", "15 min", "novel_view")].endswith("| +0.900 | within the spread |")
    assert ("0", "15 min", "novel_pose") not in rows  # no finite value on either side
    assert rows[("0", "5 min", "novel_pose")].endswith("| +0.883 | pig beyond |")  # 28.05 - 27.167 > 0.3
    assert "no spread yet" in rule_table(fits[6:])  # without the seed-0 5-minute replicates


def test_a_lever_on_both_variants_gets_its_own_rows_against_the_plain_spread():
    fits = [_final("pig", 0, 300, v) for v in (30.0, 31.0, 30.5)] + [_final("no_precond", 0, 300, 30.3)]  # NV 1.0
    fits += [_final("pig paper rates", 0, 900, 32.5), _final("no_precond paper rates", 0, 900, 31.0),  # +1.5
             _final("pig eps 1e-15", 0, 900, 31.0), _final("no_precond eps 1e-15", 0, 900, 30.8),  # +0.2
             _final("pig uniform Adam", 0, 900, 33.0)]  # no_precond's fit not run yet: no pair, no row
    lines = [line for line in rule_table(fits).splitlines() if line.startswith("| ") and "min" in line]
    assert [line.split(" | ")[0] for line in lines] == ["| -", "| eps 1e-15", "| paper rates"]
    assert lines[2].startswith("| paper rates | 0 | 15 min | novel_view | 32.50 (1) | 31.00 (1) | +1.500 | pig beyond |")
    assert lines[1].endswith("| +0.200 | within the spread |")


def test_a_lever_inert_on_the_other_variant_is_compared_with_its_plain_fits():
    """A lever that changes nothing on no_precond (the manifest's `inert`) gets rows against plain no_precond, named
    so; without `inert` a lever on pig alone gets none."""
    fits = [_final("pig", 0, 300, v) for v in (30.0, 31.0, 30.5)] + [_final("no_precond", 0, 300, 30.3)]  # NV 1.0
    fits += [_final("no_precond", 0, 900, 31.0), _final("no_precond", 0, 900, 31.4),
             {**_final("pig ramp 3000", 0, 900, 32.5), "inert": ["no_precond"]},
             _final("pig cg_tol 1e-3", 0, 900, 33.0)]
    lines = [line for line in rule_table(fits).splitlines() if line.startswith("| ") and "min" in line]
    assert [line.split(" | ")[0] for line in lines] == ["| -", "| ramp 3000 (no_precond plain: inert there)"]
    assert lines[1].endswith("| novel_view | 32.50 (1) | 31.20 (2, range 0.40) | +1.300 | pig beyond |")


def test_the_figure_gives_every_fit_label_its_own_look_and_a_lever_its_variants_colour():
    """The study's labels (17 by run37, past tab10's 10 colours, which once drew seven of them alike)."""
    labels = sorted({f["variant"] for f in load_fits(RUNS / "equal_time.yaml")})
    assert len(labels) > 10
    styles = plot_styles(labels)
    assert len(set(styles.values())) == len(labels)
    for label in labels:
        variant, _, lever = label.partition(" ")
        if lever and variant in styles:
            assert styles[label][0] == styles[variant][0] and styles[label][1] != styles[variant][1]
    same_lever = [styles[label][1] for label in labels if label.endswith(" anchor warm-up 1500")]
    assert len(same_lever) == 2 and len(set(same_lever)) == 1
    with pytest.raises(ValueError, match="levers"):
        plot_styles(["pig"] + [f"pig lever {i}" for i in range(len(LEVER_MARKERS))])

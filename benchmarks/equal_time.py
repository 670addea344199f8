"""The equal-time study's table and figure, regenerated from the fits' records (benchmarks/gpu_runs/equal_time.yaml).

Each fit listed there is one `benchmarks/fit_gpu.py --budget B --json ...` variant: its final novel view and novel
pose metrics at the finest LOD (with the synthetic subject's ground truth: garment and body PSNR, geometry, drift),
and its held-out novel-view PSNR against training seconds. Prints one Markdown table: every (seed, budget,
variant) with the mean over its replicates and, where there are several, the spread (max - min); then the held-out
novel-view PSNR read off each fit's curve at 1, 2, 5 and 10 minutes (labelled "curve": linear between the
evaluations around that time, every 1000 iterations). A fit whose JSON never came back (the hold ended during its
final evaluation) is listed with `log` and `text` instead: its curve from the train log, its final metrics from
the evaluate lines it printed, and "-" for a split it did not reach. `--plot` draws error against training time,
one panel per metric, both subjects. Last, how much each curve wobbles over its last 60 % of training seconds (a
fit's final value is one draw from that wobble): the evaluations' mean, sd and mean |dip| (each inner evaluation
against the mean of its two neighbours), and issue 38's rule: `pig` against `no_precond` per seed and budget, and
whether the difference is beyond the spread (the seed-0 5-minute replicates' max - min). A fit with a lever (extra
overrides) carries a `label` in the manifest, which names it in place of its variant. A fit with a weight average (fit.average_decay) also logs, at each evaluation after
the average started, the held-out PSNR of the iterate it averages: the last table pairs the two, within the fit. Its
last iterate, evaluated too (fit_gpu.py --evaluate-iterate) and given an `iterate_replicate` in the manifest, is a
fit of the plain variant as well (the average does not feed back into the training; only its update's time differs):

    python benchmarks/equal_time.py --plot docs/equal_time.png
"""
from __future__ import annotations

import argparse
import json
import csv
import math
import re
from collections import defaultdict
from pathlib import Path

import numpy as np
import yaml

HERE = Path(__file__).resolve().parent / "gpu_runs"
# (column, split, key in the evaluate summary, decimals): the table's metrics, finest LOD.
METRICS = [("NV PSNR", "novel_view", "psnr", 2), ("NV SSIM", "novel_view", "ssim", 4),
           ("NP PSNR", "novel_pose", "psnr", 2), ("NP SSIM", "novel_pose", "ssim", 4),
           ("garment NV dB", "novel_view", "psnr_garment", 2), ("body NV dB", "novel_view", "psnr_body", 2),
           ("garment acc / comp mm", "novel_view", ("accuracy_mm_garment", "completeness_mm_garment"), 1),
           ("body acc / comp mm", "novel_view", ("accuracy_mm_body", "completeness_mm_body"), 1),
           ("drift mm", "novel_view", "drift_mm", 1)]
CURVE_MINUTES = (1, 2, 5, 10)
WOBBLE_FROM = 0.4  # the wobble table reads the curve from this fraction of the training seconds on
SUMMARY_KEYS = ("psnr", "ssim", "psnr_garment", "psnr_body", "accuracy_mm_garment", "completeness_mm_garment",
                "accuracy_mm_body", "completeness_mm_body", "drift_mm")
# The evaluate stage's printed summary of one split and LOD (pig/stages/evaluate.py), images, then regions.
NUMBER = r"(-?[\d.]+|nan)"
IMAGE_LINE = re.compile(rf"\[evaluate\] (\w+) lod(\d+): PSNR {NUMBER} SSIM {NUMBER} ")
REGION_LINE = re.compile(
    rf"\[evaluate\] (\w+) lod(\d+): PSNR garment {NUMBER} body {NUMBER} background {NUMBER}; accuracy garment "
    rf"{NUMBER} body {NUMBER} mm, completeness garment {NUMBER} body {NUMBER} mm, drift {NUMBER} mm")


def load_fits(manifest: Path) -> list[dict]:
    """The manifest's fits, each with its final metrics, iterations, ms/it and held-out curve [(train s, dB)]; an
    averaged fit whose last iterate was evaluated too (fit_gpu.py --evaluate-iterate) and whose entry gives it an
    `iterate_replicate` number is also that replicate of its plain variant."""
    entries = yaml.safe_load(manifest.read_text())["fits"]
    fits = []
    for entry in entries:
        fit = fit_from_json(manifest.parent, entry) if "json" in entry else fit_from_log(manifest.parent, entry)
        fits.append({**fit, "variant": fit.get("label", fit["variant"])})
        if "iterate_replicate" in entry:
            fits.append(iterate_fit(manifest.parent, fit))
    return fits


def iterate_fit(root: Path, fit: dict) -> dict:
    """The plain variant's fit that an averaged fit's last iterate is: its own final metrics, and the held-out curve
    of the iterate (the logged PSNR before the average started, the iterate's beside the average's after)."""
    curve = [(float(r["train_s"]), float(r["heldout_psnr_iterate"] or r["heldout_psnr"]))
             for r in log_rows(root, fit) if r["heldout_psnr"]]
    plain = {key: value for key, value in fit.items() if key not in ("label", "overrides", "final_iterate")}
    return {**plain, "replicate": fit["iterate_replicate"],
            "iterate_of": f"{fit.get('label', fit['variant'])} #{fit['replicate']}", "final": fit["final_iterate"],
            "curve": curve}


def finest_levels(budget: dict) -> dict:
    """{split: the finest LOD's summary} of a fit_gpu.py budget record."""
    return {split: budget[split][max(budget[split], key=int)] for split in ("novel_view", "novel_pose")}


def averaged_pairs(root: Path, entry: dict) -> list[tuple[float, float, float]]:
    """[(train s, held-out PSNR of the average, of its iterate)] at the evaluations where the fit logged both."""
    return [(float(r["train_s"]), float(r["heldout_psnr"]), float(r["heldout_psnr_iterate"]))
            for r in log_rows(root, entry) if r.get("heldout_psnr_iterate") and r["heldout_psnr"]]


def fit_from_json(root: Path, entry: dict) -> dict:
    record = json.loads((root / entry["json"]).read_text())["results"]
    [result] = [r for r in record if r.get("budget")]
    budget = result["budget"]
    iterate = {"final_iterate": finest_levels(result["budget_iterate"])} if "budget_iterate" in result else {}
    return {**entry, **iterate, "variant": result["variant"], "final": finest_levels(budget),
            "iterations": budget["iterations"],
            "train_s": budget["train_s"], "compile_s": budget.get("compile_s", math.nan),
            "ms_per_iteration": result["ms_per_iteration"], "curve": [tuple(p) for p in result["heldout_by_time"]]}


def log_rows(root: Path, entry: dict) -> list[dict]:
    """The rows of the fit's train log."""
    with open(root / entry["log"], newline="") as file:
        return list(csv.DictReader(file))


def fit_from_log(root: Path, entry: dict) -> dict:
    rows = log_rows(root, entry)
    last = rows[-1]
    curve = [(float(r["train_s"]), float(r["heldout_psnr"])) for r in rows if r["heldout_psnr"]]
    return {**entry, "final": printed_metrics((root / entry["text"]).read_text()), "iterations": int(last["iteration"]),
            "train_s": float(last["train_s"]), "compile_s": float(last["compile_s"]), "ms_per_iteration": math.nan,
            "curve": curve}


def printed_metrics(text: str) -> dict:
    """{split: summary} of the finest LOD each split printed; NaN for what is missing."""
    found: dict[str, dict[int, dict]] = {split: defaultdict(dict) for split in ("novel_view", "novel_pose")}
    for match in IMAGE_LINE.finditer(text):
        found[match[1]][int(match[2])].update(psnr=float(match[3]), ssim=float(match[4]))
    for match in REGION_LINE.finditer(text):
        values = [float(v) for v in match.groups()[2:]]
        found[match[1]][int(match[2])].update(zip(("psnr_garment", "psnr_body", "psnr_background",
                                                   "accuracy_mm_garment", "accuracy_mm_body", "completeness_mm_garment",
                                                   "completeness_mm_body", "drift_mm"), values))
    return {split: {key: lods[max(lods)].get(key, math.nan) if lods else math.nan for key in SUMMARY_KEYS}
            for split, lods in found.items()}


def metric(fit: dict, split: str, key) -> float | tuple[float, float]:
    values = fit["final"][split]
    return tuple(values[k] for k in key) if isinstance(key, tuple) else values[key]


def read_off(curve: list[tuple[float, float]], seconds: float) -> float:
    """The held-out PSNR at `seconds`, linear between the evaluations around it (NaN past the curve's end)."""
    if not curve or curve[-1][0] < seconds - 1.0:
        return math.nan
    times, values = zip(*curve)
    return float(np.interp(seconds, times, values))


def wobble(curve: list[tuple[float, float]]) -> tuple[int, float, float, float]:
    """(evaluations, mean, sd, mean |dip|) of the held-out PSNR over the curve's late part (NaN where too short)."""
    late = np.array([psnr for seconds, psnr in curve if seconds >= WOBBLE_FROM * curve[-1][0]]) if curve else []
    if len(late) < 3:
        return len(late), math.nan, math.nan, math.nan
    dips = late[1:-1] - (late[:-2] + late[2:]) / 2
    return len(late), float(late.mean()), float(late.std()), float(np.abs(dips).mean())


def cell(values: list, decimals: int) -> str:
    if isinstance(values[0], tuple):
        return " / ".join(cell([v[i] for v in values], decimals) for i in range(len(values[0])))
    known = [v for v in values if not math.isnan(v)]
    if not known:
        return "-"
    text = f"{float(np.mean(known)):.{decimals}f}"
    if len(known) > 1:
        text += f" ± {(max(known) - min(known)) / 2:.{decimals}f}"
    # A fit whose split never came back (device time ran out) leaves the others' mean, said as such.
    return text + (f" ({len(known)} of {len(values)})" if len(known) < len(values) else "")


def averaged_table(root: Path, fits: list[dict]) -> str:
    """Each averaged fit's held-out PSNR, average against iterate at the same evaluations (empty: none averaged)."""
    lines = []
    for fit in fits:
        pairs = averaged_pairs(root, fit) if "log" in fit and "iterate_of" not in fit else []
        if not pairs:
            continue
        gains = [average - iterate for _, average, iterate in pairs]
        lines.append(f"| {fit['seed']} | {fit['budget_s'] / 60:g} min | {fit['variant']} | {fit['replicate']} | "
                     + ", ".join(f"{t:.0f}: {a:.2f} / {i:.2f}" for t, a, i in pairs)
                     + f" | {np.mean(gains):+.2f} ({min(gains):+.2f} to {max(gains):+.2f}) |")
    if not lines:
        return ""
    return "\n".join(["", "Weight average against its own iterate, held-out novel-view PSNR at the same evaluations", "",
                      "| seed | budget | fit | # | train s: average / iterate dB | average - iterate dB: mean (range) |",
                      "|---|---|---|---|---|---|"] + lines)


def table(fits: list[dict]) -> str:
    groups: dict[tuple, list[dict]] = defaultdict(list)
    for fit in fits:
        groups[(fit["seed"], fit["budget_s"], fit["variant"])].append(fit)
    lines = ["| seed | budget | variant | fits | iterations | " + " | ".join(m[0] for m in METRICS) + " |",
             "|---|---|---|---|---|" + "---|" * len(METRICS)]
    for (seed, budget, variant), group in sorted(groups.items()):
        cells = [cell([metric(f, split, key) for f in group], decimals) for _, split, key, decimals in METRICS]
        iterations = "/".join(str(f["iterations"]) for f in group)
        lines.append(f"| {seed} | {budget / 60:g} min | {variant} | {len(group)} | {iterations} | " + " | ".join(cells) + " |")
    ordered = sorted(fits, key=lambda f: (f["seed"], f["budget_s"], f["variant"], f["replicate"]))
    lines += ["", "Held-out novel-view PSNR read off the curves (curve: linear between the evaluations around the time)", "",
              "| seed | budget | variant | fit | " + " | ".join(f"{m} min (curve)" for m in CURVE_MINUTES) + " |",
              "|---|---|---|---|" + "---|" * len(CURVE_MINUTES)]
    for fit in ordered:
        values = [read_off(fit["curve"], 60 * m) for m in CURVE_MINUTES]
        lines.append(f"| {fit['seed']} | {fit['budget_s'] / 60:g} min | {fit['variant']} | {fit['replicate']} | "
                     + " | ".join("-" if math.isnan(v) else f"{v:.2f}" for v in values) + " |")
    lines += ["", f"Wobble of the held-out novel-view PSNR from {WOBBLE_FROM:.0%} of the training seconds on", "",
              "| seed | budget | variant | fit | evaluations | mean dB | sd dB | mean abs dip dB | final dB |",
              "|---|---|---|---|---|---|---|---|---|"]
    for fit in ordered:
        count, mean, sd, dip = wobble(fit["curve"])
        final = fit["curve"][-1][1] if fit["curve"] else math.nan
        lines.append(f"| {fit['seed']} | {fit['budget_s'] / 60:g} min | {fit['variant']} | {fit['replicate']} | "
                     f"{count} | " + " | ".join("-" if math.isnan(v) else f"{v:.2f}" for v in (mean, sd, dip, final))
                     + " |")
    return "\n".join(lines)


def mean_and_range(values: list[float]) -> str:
    """A rule cell: the mean and how many fits, with their max - min where there are several (a lever's own range,
    to read beside the rule's spread)."""
    spread = f", range {max(values) - min(values):.2f}" if len(values) > 1 else ""
    return f"{np.mean(values):.2f} ({len(values)}{spread})"


def rule_table(fits: list[dict], leader: str = "pig", other: str = "no_precond") -> str:
    """Issue 38's rule, where both variants have fits: the mean final novel-view and novel-pose PSNR of `leader` and
    `other` per seed and budget, their difference, and whether it is beyond the spread, the larger of the two
    variants' max - min over the seed-0 5-minute replicates (the issue's definition), split by split. A lever is a
    pair of labels `leader LEVER` and `other LEVER` (e.g. "pig average 0.99", "no_precond average 0.99"): its rows
    follow the plain variants', against the same spread. A lever that changes nothing on `other` (a manifest entry's
    `inert: [no_precond]`, e.g. the grid's ramp: no_precond has no preconditioner) is compared with plain `other`."""
    def finals(variant, seed, budget, split):
        return [v for f in fits if (f["variant"], f["seed"], f["budget_s"]) == (variant, seed, budget)
                for v in [metric(f, split, "psnr")] if not math.isnan(v)]

    spreads = {}
    for split in ("novel_view", "novel_pose"):
        ranges = [max(v) - min(v) for v in (finals(leader, 0, 300, split), finals(other, 0, 300, split)) if len(v) > 1]
        spreads[split] = max(ranges) if ranges else math.nan
    names = {f["variant"] for f in fits}
    inert = {f["variant"][len(leader):] for f in fits
             if f["variant"].startswith(leader + " ") and other in f.get("inert", ())}
    levers = [""] + sorted(name[len(leader):] for name in names
                           if name.startswith(leader + " ") and (other + name[len(leader):] in names
                                                                 or name[len(leader):] in inert))
    lines = ["", f"Issue 38's rule: `{leader}` against `{other}`, beyond the spread (the larger of the two variants' "
             f"max - min over the seed-0 5-minute replicates: novel view {spreads['novel_view']:.3f} dB, novel pose "
             f"{spreads['novel_pose']:.3f} dB)", "",
             f"| lever | seed | budget | split | {leader} dB (fits, range) | {other} dB (fits, range) | difference dB "
             "| verdict |",
             "|---|---|---|---|---|---|---|---|"]
    for lever in levers:
        partner = other if lever in inert else other + lever
        name = f"{lever.strip()} ({other} plain: inert there)" if lever in inert else lever.strip() or "-"
        for seed, budget in sorted({(f["seed"], f["budget_s"]) for f in fits}):
            for split in ("novel_view", "novel_pose"):
                mine, theirs = finals(leader + lever, seed, budget, split), finals(partner, seed, budget, split)
                if not (mine and theirs):
                    continue
                difference = float(np.mean(mine) - np.mean(theirs))
                if math.isnan(spreads[split]):
                    verdict = "no spread yet"
                elif abs(difference) > spreads[split]:
                    verdict = f"{leader if difference > 0 else other} beyond"
                else:
                    verdict = "within the spread"
                lines.append(f"| {name} | {seed} | {budget / 60:g} min | {split} | {mean_and_range(mine)} | "
                             f"{mean_and_range(theirs)} | {difference:+.3f} | {verdict} |")
    return "\n".join(lines)


LEVER_MARKERS = "o^vDPX*<>hpd"


def plot_styles(labels: list[str]) -> dict[str, tuple[int, str]]:
    """Each fit label's (colour index, marker): the colour names the variant (the label's first word), the marker the
    lever after it ("o" for the plain fit), so that a lever fit reads beside its plain partner."""
    variants = sorted({label.split(" ", 1)[0] for label in labels})
    levers = sorted({label.partition(" ")[2] for label in labels} - {""})
    if len(variants) > 10 or len(levers) >= len(LEVER_MARKERS):
        raise ValueError(f"{len(variants)} variants and {len(levers)} levers: the figure tells apart at most 10 "
                         f"and {len(LEVER_MARKERS) - 1}")
    markers = {"": LEVER_MARKERS[0]} | {lever: LEVER_MARKERS[i + 1] for i, lever in enumerate(levers)}
    return {label: (variants.index(label.split(" ", 1)[0]), markers[label.partition(" ")[2]]) for label in labels}


def plot(fits: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = [("held-out NV PSNR (curve) [dB]", None)] + [(m[0], m) for m in METRICS if m[0] != "NV SSIM"]
    columns = 4
    rows = math.ceil(len(panels) / columns)
    fig, axes = plt.subplots(rows, columns, figsize=(4 * columns, 3.2 * rows), squeeze=False)
    labels = sorted({f["variant"] for f in fits})
    styles = plot_styles(labels)
    line_styles = {0: "-", 1: "--"}

    def look(label: str, seed: int) -> dict:  # seed 1 hollow, so the seeds stay apart where the points overlap
        colour, marker = styles[label]
        return {"color": plt.cm.tab10(colour), "marker": marker,
                "markerfacecolor": "none" if seed else plt.cm.tab10(colour)}

    for ax, (title, spec) in zip(axes.flat, panels):
        for fit in fits:
            kwargs = look(fit["variant"], fit["seed"])
            if spec is None:
                t, psnr = zip(*fit["curve"][1:])  # the start (0 s, untrained) would squash the axis
                ax.plot(np.array(t) / 60, psnr, line_styles.get(fit["seed"], ":"), alpha=0.8, markersize=3,
                        linewidth=1, **kwargs)
            else:
                value = metric(fit, spec[1], spec[2])
                value = value[0] if isinstance(value, tuple) else value  # geometry: accuracy
                if math.isnan(value):
                    continue
                ax.plot(fit["budget_s"] / 60, value, linestyle="none", alpha=0.8, **kwargs)
        ax.set_title(title if spec is None or not isinstance(spec[2], tuple) else title.split(" / ")[0] + " mm",
                     fontsize=9)
        ax.set_xlabel("training minutes")
        ax.set_xlim(0, max(f["budget_s"] for f in fits) / 60 + 1)
        ax.grid(alpha=0.3)
    for ax in list(axes.flat)[len(panels):]:
        ax.axis("off")
    colours = {label.split(" ", 1)[0]: colour for label, (colour, _) in styles.items()}
    handles = [plt.Line2D([], [], color=plt.cm.tab10(colour), label=v) for v, colour in sorted(colours.items())]
    handles += [plt.Line2D([], [], color="k", linestyle="none", marker=marker, label=lever or "no lever")
                for lever, marker in sorted({(lab.partition(" ")[2], m) for lab, (_, m) in styles.items()})]
    handles += [plt.Line2D([], [], color="k", linestyle=line_styles[s], marker="o",
                           markerfacecolor="none" if s else "k", label=f"seed {s}")
                for s in sorted({f["seed"] for f in fits})]
    fig.legend(handles=handles, loc="lower right", fontsize=8, ncol=2)
    fig.suptitle("Equal training time (compilation, evaluations and checkpoints left out), finest LOD; colour: "
                 "variant, marker: lever", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=90)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--manifest", type=Path, default=HERE / "equal_time.yaml")
    parser.add_argument("--plot", type=Path, default=None, help="write the figure here")
    args = parser.parse_args(argv)
    fits = load_fits(args.manifest)
    print(table(fits))
    for fit in fits:
        if "iterate_of" in fit:
            print(f"\n{fit['hold']} seed {fit['seed']} {fit['variant']} #{fit['replicate']}: the last iterate of "
                  f"{fit['iterate_of']}", end="")
            continue
        print(f"\n{fit['hold']} seed {fit['seed']} {fit['variant']} #{fit['replicate']} ({fit['device']}): "
              f"{fit['iterations']} iterations, "
              + ("" if math.isnan(fit["ms_per_iteration"]) else f"{fit['ms_per_iteration']:.1f} ms/it, ")
              + f"{fit['train_s']:.0f} training s, "
              f"{fit['compile_s']:.0f} s of compilation left out", end="")
    print()
    print(averaged_table(args.manifest.parent, fits))
    print(rule_table(fits))
    if args.plot is not None:
        plot(fits, args.plot)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Tables stage: the paper's result tables from the evaluate stage's summaries, as CSV and Markdown, plus a plot.

Layouts of Section 4: Tables 1-2 (variants x novel-view / novel-pose PSNR, SSIM, LPIPS, FID, splats),
the LOD table (splats, metrics, model MB, FPS per level), and held-out PSNR against training time.
The LPIPS columns carry their backbone in the header (`novel_view_lpips_vgg`, `lpips_alex`, ...). Each FID
column has two numeric companions, `..._fid_images` (images per set; the smallest over the subjects
averaged) and `..._fid_biased` (1 when a set had fewer than the evaluate stage's `fid_min_images`); the
Markdown shows them in the FID cell, as `123.40 (N=36, biased)`.
"""
from __future__ import annotations

import argparse
import math
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import pandas as pd  # noqa: E402

from pig.stages._cli import add_common_arguments, run_cli  # noqa: E402
from pig.stages._io import read_record, write_figure, write_text  # noqa: E402
from pig.stages._outputs import claim_files  # noqa: E402

SPLITS = ("novel_view", "novel_pose")
METRICS = ("psnr", "ssim", "lpips", "fid")
FID_COUNT = ("fid_images", "fid_min_images")
BLANK_ROW = "blank (black image)"


def read_summaries(paths: list[Path]) -> pd.DataFrame:
    """One row per summary file results/{dataset}/{subject}/{variant}/metrics/{split}_lod{l}.json."""
    rows = []
    for path in paths:
        path = Path(path)
        if path.parent.name != "metrics" or len(path.parts) < 4:
            raise ValueError(f"{path}: expected a summary at .../{{subject}}/{{variant}}/metrics/{{split}}_lod{{l}}.json")
        summary = read_record(path, "an evaluate summary")  # the evaluate stage writes NaN as null
        missing = {"split", "lod", "splats", *METRICS} - set(summary)
        if missing:
            raise ValueError(f"{path}: summary lacks keys {sorted(missing)}")
        if not math.isnan(summary["fid"]) and not set(FID_COUNT) <= set(summary):
            raise ValueError(f"{path}: summary has a FID but not the image count it was computed over (no "
                             f"{' / '.join(FID_COUNT)}: written by an older evaluate stage); re-run evaluate")
        rows.append({"subject": path.parts[-4], "variant": path.parts[-3], **summary})
    if not rows:
        raise ValueError("no evaluate summaries given")
    return pd.DataFrame(rows)


def _notes(frame: pd.DataFrame) -> str:
    notes = sorted({n for col in ("lpips_note", "fid_note", "fit_note") if col in frame for n in frame[col].dropna() if n})
    return "; ".join(notes)


def fid_count(summaries: pd.DataFrame) -> tuple[float, float]:
    """(images, biased) of the FIDs one table cell averages: the smallest set's image count, and 1.0 when any
    set had fewer than its `fid_min_images` (the estimate's bias grows as 1/N), else 0.0; NaN without a FID."""
    scored = summaries[summaries["fid"].notna()]
    if scored.empty:
        return math.nan, math.nan
    return float(scored["fid_images"].min()), float((scored["fid_images"] < scored["fid_min_images"]).any())


def lpips_column(summaries: pd.DataFrame) -> str:
    """`lpips_alex` or `lpips_vgg`: the LPIPS column named after the one backbone all summaries were scored with.

    Peers report LPIPS with either backbone and the values differ, so a table never averages or hides them.
    """
    def name(row) -> str:
        return f"{row['subject']}/{row['variant']}/metrics/{row['split']}_lod{row['lod']}.json"

    nets = summaries["lpips_net"] if "lpips_net" in summaries else pd.Series(math.nan, index=summaries.index)
    unnamed = summaries[nets.isna()]
    if not unnamed.empty:
        raise ValueError(f"{name(unnamed.iloc[0])}: summary does not name its LPIPS backbone (no 'lpips_net': "
                         "written by an older evaluate stage); re-run evaluate")
    if nets.nunique() > 1:
        examples = {net: name(summaries[nets == net].iloc[0]) for net in sorted(nets.unique())}
        raise ValueError(f"summaries were scored with different LPIPS backbones ({examples}); evaluate every "
                         "subject and variant with one `evaluate.lpips_net`")
    return f"lpips_{nets.iloc[0]}"


def main_table(summaries: pd.DataFrame, variants: list[str]) -> pd.DataFrame:
    """Tables 1-2: per variant (finest LOD, mean over subjects) novel-view and novel-pose metrics and splats."""
    lpips = lpips_column(summaries)
    finest = summaries[summaries["lod"] == summaries.groupby("variant")["lod"].transform("max")]
    rows = []
    for variant in variants:
        part = finest[finest["variant"] == variant]
        if part.empty:
            raise ValueError(f"no summaries for variant {variant!r}; found {sorted(summaries['variant'].unique())}")
        row = {"variant": variant}
        for split in SPLITS:
            rows_split = part[part["split"] == split]
            for metric in METRICS:
                row[f"{split}_{metric}"] = rows_split[metric].mean() if not rows_split.empty else math.nan
            row[f"{split}_fid_images"], row[f"{split}_fid_biased"] = fid_count(rows_split)
        row["splats"] = int(part["splats"].max())
        row["notes"] = _notes(part)
        rows.append(row)
    # A black image scored against the masked ground truth: the floor every method must clear.
    blank = {"variant": BLANK_ROW}
    for split in SPLITS:
        rows_split = finest[finest["split"] == split]
        blank.update({f"{split}_psnr": rows_split["psnr_blank"].mean(), f"{split}_ssim": rows_split["ssim_blank"].mean(),
                      f"{split}_lpips": math.nan, f"{split}_fid": math.nan, f"{split}_fid_images": math.nan,
                      f"{split}_fid_biased": math.nan})
    blank.update(splats=0, notes=f"{BLANK_ROW}: an all-black render scored like the methods (PSNR and SSIM only)")
    rows.append(blank)
    return pd.DataFrame(rows).rename(columns={f"{split}_lpips": f"{split}_{lpips}" for split in SPLITS})


def lod_table(summaries: pd.DataFrame, variants: list[str], split: str = "novel_view") -> pd.DataFrame:
    """The LOD table: per variant and level, splats, metrics, model MB and FPS (mean over subjects)."""
    lpips = lpips_column(summaries)
    rows = []
    for variant in variants:
        part = summaries[(summaries["variant"] == variant) & (summaries["split"] == split)]
        levels = sorted(part["lod"].unique())
        for level in levels:
            at = part[part["lod"] == level]
            rows.append({
                "variant": variant,
                "lod": f"{level + 1}/{len(levels)}",
                "splats": int(at["splats"].max()),
                **{metric: at[metric].mean() for metric in METRICS},
                **dict(zip(("fid_images", "fid_biased"), fid_count(at))),
                "mb": at["model_mb"].mean(),
                "fps": at["fps"].mean(),
                "device": "; ".join(sorted(at["device"].unique())),
                "notes": _notes(at),
            })
    return pd.DataFrame(rows).rename(columns={"lpips": lpips})


def to_markdown(table: pd.DataFrame, title: str) -> str:
    """A GitHub Markdown table; NaN prints as 'n/a', a FID carries its image count and bias flag in its cell
    (`123.40 (N=36, biased)`), and the notes column becomes a list below the table."""
    notes = sorted({n for cell in table.get("notes", []) for n in str(cell).split("; ") if n})

    def cell(value) -> str:
        if isinstance(value, float):
            if math.isnan(value):
                return "n/a"
            return f"{value:.3f}" if abs(value) < 10 else f"{value:.2f}"
        return str(value)

    shown = table.drop(columns=["notes"], errors="ignore")
    for column in [c for c in shown.columns if f"{c}_images" in shown and f"{c}_biased" in shown]:
        images, biased = shown.pop(f"{column}_images"), shown.pop(f"{column}_biased")
        shown[column] = [cell(value) if math.isnan(value) else
                         f"{cell(value)} (N={int(n)}{', biased' if b else ''})"
                         for value, n, b in zip(table[column], images, biased)]
    lines = [f"## {title}", "", "| " + " | ".join(shown.columns) + " |", "|" + "---|" * len(shown.columns)]
    lines += ["| " + " | ".join(cell(v) for v in row) + " |" for row in shown.itertuples(index=False)]
    if notes:
        lines += ["", "Notes:", ""] + [f"- {note}" for note in notes]
    return "\n".join(lines) + "\n"


def read_train_log(path: Path) -> pd.DataFrame:
    """Wall time and held-out PSNR of one train_log.csv, checked: numbers, both columns present."""
    columns = ["wall_s", "heldout_psnr"]
    try:
        log = pd.read_csv(path)
    except (OSError, UnicodeDecodeError, pd.errors.ParserError, pd.errors.EmptyDataError) as err:
        raise ValueError(f"{path}: not a readable train log ({err})") from None
    if not set(columns) <= set(log.columns):
        raise ValueError(f"{path}: train log lacks columns {sorted(set(columns) - set(log.columns))}; found {list(log.columns)}")
    try:
        return log[columns].apply(pd.to_numeric)
    except (ValueError, TypeError) as err:
        raise ValueError(f"{path}: train log has a non-numeric wall_s or heldout_psnr ({err})") from None


def training_plot(logs: dict[str, dict[Path, pd.DataFrame]], path: Path, title: str) -> None:
    """Held-out PSNR against training wall time, one line per (variant, subject), from `read_train_log`."""
    fig, ax = plt.subplots(figsize=(6, 4), dpi=120)
    for variant, files in logs.items():
        for file, log in files.items():
            log = log.dropna(subset=["heldout_psnr"])
            ax.plot(log["wall_s"], log["heldout_psnr"], marker="o", markersize=3, label=f"{variant} ({Path(file).parts[-3]})")
    ax.set_xlabel("training wall time [s]")
    ax.set_ylabel("held-out novel-view PSNR [dB]")
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    write_figure(path, fig)


def make_tables(dataset: str, summaries: list[Path], train_logs: list[Path], variants: list[str], output: Path,
                overwrite: bool = False) -> None:
    """Write the tables and the training plot to `output`, after every input has been read and checked; files
    of the same names are replaced only in a tables output folder, or with `overwrite`."""
    table = read_summaries(summaries)
    main = main_table(table, variants)
    lod = lod_table(table, variants)
    logs = {v: {p: read_train_log(p) for p in map(Path, train_logs) if p.parent.name == v} for v in variants}
    texts = {
        f"{dataset}.csv": main.to_csv(index=False, float_format="%.6g"),
        f"{dataset}.md": to_markdown(main, f"{dataset}: novel views and novel poses (finest LOD)"),
        f"{dataset}_lod.csv": lod.to_csv(index=False, float_format="%.6g"),
        f"{dataset}_lod.md": to_markdown(lod, f"{dataset}: levels of detail (novel views)"),
    }
    plot = f"{dataset}_training.png"
    claim_files(output, [*texts, plot], "tables", [*summaries, *train_logs], overwrite)
    for name, text in texts.items():
        write_text(output / name, text)
    training_plot(logs, output / plot, f"{dataset}: held-out PSNR during training")
    print(to_markdown(main, dataset))
    print(to_markdown(lod, f"{dataset} LOD"))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m pig.stages.tables", description=__doc__.splitlines()[0])
    parser.add_argument("--dataset", required=True)
    parser.add_argument("--summaries", type=Path, nargs="+", required=True, help="metrics/{split}_lod{l}.json files")
    parser.add_argument("--train-logs", type=Path, nargs="*", default=[], help="{variant}/train_log.csv files")
    parser.add_argument("--variants", nargs="+", required=True, help="row order of the tables")
    parser.add_argument("--output", type=Path, required=True, help="tables directory (results/tables)")
    add_common_arguments(parser)
    parser.add_argument("--overwrite", action="store_true",
                        help="replace files of the same names in an --output folder the tables stage did not write")
    args = parser.parse_args(argv)
    make_tables(args.dataset, args.summaries, args.train_logs, args.variants, args.output, args.overwrite)
    return 0


if __name__ == "__main__":
    raise SystemExit(run_cli(main))

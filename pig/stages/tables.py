"""Tables stage: the paper's result tables from the evaluate stage's summaries, as CSV, Markdown and HTML, plus a plot.

Layouts of Section 4 (`--table`):
- `main`: Tables 1-2 (variant, then novel-view and novel-pose PSNR, SSIM, LPIPS, FID, then splats), `{dataset}.csv`; the
  LOD table (splats, metrics, model MB, FPS per level; a single-level variant such as `lod_1of1` is its `1/1`
  row), `{dataset}_lod.csv`; held-out PSNR against training wall time of every variant, `{dataset}_training.png`.
- `ablation`: the structural ablation (Table 4) in the main table's layout, `{dataset}_ablation.csv`.
- `noise`: robustness to body-parameter noise (Table 5): the main layout per sigma_body (radians on the pose,
  and in degrees), `{dataset}_noise.csv`; sigma comes from the preset the variants were fitted with.
- `regions`: the ground-truth metrics of synthetic captures per variant and split, `{dataset}_regions.csv`.
Summaries of captures with ground truth carry REGION_KEYS (PSNR/SSIM per region, geometry error and
correspondence drift in mm); they go to the regions table, and the ablation and noise tables (whose subjects the
regions table does not cover) gain a `{split}_{key}` column each; real captures have none. The regions table is
refused when no summary has them.
The LPIPS columns carry their backbone in the header (`novel_view_lpips_vgg`, `lpips_alex`, ...). Each FID
column has two numeric companions, `..._fid_images` (images per set; the smallest over the subjects
averaged) and `..._fid_biased` (1 when a set had fewer than the evaluate stage's `fid_min_images`); the
Markdown and HTML show them as a footnote on the FID cell.
Each table is `{name}.csv` (full precision), `{name}.md` and `{name}.html` (rounded as papers print them, notes as
footnotes: pig.metrics.table_format; the HTML is the report's page).
"""
from __future__ import annotations

import io
import math
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import pandas as pd  # noqa: E402

from pig.names import safe_name  # noqa: E402
from pig._cli import add_common_arguments, add_preset_argument, run_cli, stage_parser  # noqa: E402
from pig._io import read_record, write_figure, write_text  # noqa: E402
from pig._outputs import claim_files  # noqa: E402
from pig.metrics.table_format import read_table, to_html, to_markdown  # noqa: E402

SPLITS = ("novel_view", "novel_pose")
METRICS = ("psnr", "ssim", "lpips", "fid")
FID_COUNT = ("fid_images", "fid_min_images")
BLANK_ROW = "blank (black image)"
# Ground-truth metrics of the evaluate summaries of synthetic captures (absent for real captures).
REGION_KEYS = ("psnr_garment", "psnr_body", "psnr_background", "ssim_garment", "ssim_body", "ssim_background",
               "accuracy_mm_garment", "accuracy_mm_body", "completeness_mm_garment", "completeness_mm_body",
               "drift_mm", "drift_mm_last")
TABLES = ("main", "ablation", "noise", "regions")


def read_summaries(paths: list[Path]) -> pd.DataFrame:
    """One row per summary file results/{dataset}/{subject}/{variant}/metrics/{split}_lod{l}.json.

    Either every summary has all REGION_KEYS or none has any: a table never mixes scored and unscored rows."""
    rows, with_regions, without_regions, seen = [], None, None, {}
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
        regions = set(REGION_KEYS) & set(summary)
        if regions and regions != set(REGION_KEYS):
            raise ValueError(f"{path}: summary has only some ground-truth region metrics, lacks "
                             f"{sorted(set(REGION_KEYS) - regions)}; re-run evaluate")
        if regions:
            with_regions = with_regions or path
        else:
            without_regions = without_regions or path
        key = (path.parts[-4], path.parts[-3], summary["split"], summary["lod"])
        if key in seen:  # one run found in two result trees: averaging them would score neither
            raise ValueError(f"{path}: a second summary of subject {key[0]!r}, variant {key[1]!r}, split {key[2]!r}, "
                             f"LOD {key[3]} (the first is {seen[key]}); pass one summary per run")
        seen[key] = path
        rows.append({"subject": path.parts[-4], "variant": path.parts[-3], **summary})
    if not rows:
        raise ValueError("no evaluate summaries given")
    if with_regions and without_regions:
        raise ValueError(f"{without_regions}: summary lacks the ground-truth region metrics ({', '.join(REGION_KEYS)}) "
                         f"that {with_regions} has: written by an older evaluate stage, or a capture without ground "
                         "truth among captures with it; re-run evaluate")
    return pd.DataFrame(rows)


def has_regions(summaries: pd.DataFrame) -> bool:
    """Whether the summaries carry the ground-truth region metrics (all of them do, or none; `read_summaries`)."""
    return REGION_KEYS[0] in summaries


def _notes(frame: pd.DataFrame) -> str:
    notes = sorted({n for col in ("lpips_note", "fid_note", "fit_note", "protocol_note", "weights_note", "precision_note") if col in frame for n in frame[col].dropna() if n})
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


def protocol_suffix(summaries: pd.DataFrame) -> str:
    """'' for this project's protocol (`ours`; summaries without the key were scored by it), else `_{protocol}`,
    which the columns of the metrics a peer's protocol changes (SSIM, LPIPS, FID) carry. Mixed protocols are refused."""
    names = summaries["protocol"].fillna("ours") if "protocol" in summaries else pd.Series("ours", index=summaries.index)
    if names.nunique() > 1:
        raise ValueError(f"summaries were scored by different protocols ({sorted(names.unique())}); evaluate every "
                         "subject and variant with one `evaluate.protocol`")
    return "" if names.iloc[0] == "ours" else f"_{names.iloc[0]}"


def _metric_names(lpips: str, suffix: str) -> dict[str, str]:
    return {"psnr": "psnr", "ssim": f"ssim{suffix}", "lpips": f"{lpips}{suffix}", "fid": f"fid{suffix}"}


def finest_rows(summaries: pd.DataFrame) -> pd.DataFrame:
    """The summaries at each variant's finest LOD."""
    return summaries[summaries["lod"] == summaries.groupby("variant")["lod"].transform("max")]


def finest_by_variant(summaries: pd.DataFrame, variants: list[str]):
    """(variant, its summaries at its finest LOD) for each of `variants`, in order; a variant without any is refused."""
    finest = finest_rows(summaries)
    for variant in variants:
        part = finest[finest["variant"] == variant]
        if part.empty:
            raise ValueError(f"no summaries for variant {variant!r}; found {sorted(summaries['variant'].unique())}")
        yield variant, part


def main_table(summaries: pd.DataFrame, variants: list[str], blank: bool = True, regions: bool = True) -> pd.DataFrame:
    """Tables 1-2: per variant (finest LOD, mean over subjects) novel-view and novel-pose metrics and splats,
    then, with `regions`, `{split}_{key}` per REGION_KEYS where the summaries have them; with `blank`, the
    black-image row."""
    lpips = lpips_column(summaries)
    regions = REGION_KEYS if regions and has_regions(summaries) else ()
    rows = []
    for variant, part in finest_by_variant(summaries, variants):
        row = {"variant": variant}
        for split in SPLITS:
            rows_split = part[part["split"] == split]
            for metric in METRICS:
                row[f"{split}_{metric}"] = rows_split[metric].mean() if not rows_split.empty else math.nan
            row[f"{split}_fid_images"], row[f"{split}_fid_biased"] = fid_count(rows_split)
        row["splats"] = int(part["splats"].max())
        for split in SPLITS:
            rows_split = part[part["split"] == split]
            row.update({f"{split}_{key}": rows_split[key].mean() if not rows_split.empty else math.nan for key in regions})
        row["notes"] = _notes(part)
        rows.append(row)
    if blank:
        rows.append(_blank_row(finest_rows(summaries), regions))
    names = _metric_names(lpips, protocol_suffix(summaries))
    return pd.DataFrame(rows).rename(columns={f"{split}_{m}": f"{split}_{names[m]}" for split in SPLITS for m in METRICS})


def _blank_row(finest: pd.DataFrame, regions: tuple[str, ...]) -> dict:
    """A black image scored against the masked ground truth: the floor every method must clear."""
    row = {"variant": BLANK_ROW}
    for split in SPLITS:
        rows_split = finest[finest["split"] == split]
        row.update({f"{split}_psnr": rows_split["psnr_blank"].mean(), f"{split}_ssim": rows_split["ssim_blank"].mean(),
                    f"{split}_lpips": math.nan, f"{split}_fid": math.nan, f"{split}_fid_images": math.nan,
                    f"{split}_fid_biased": math.nan})
    row["splats"] = 0
    row.update({f"{split}_{key}": math.nan for split in SPLITS for key in regions})
    row["notes"] = f"{BLANK_ROW}: an all-black render scored like the methods (PSNR and SSIM only)"
    return row


def noise_table(summaries: pd.DataFrame, sigmas: dict[str, float]) -> pd.DataFrame:
    """Table 5: the main layout per variant with its body-parameter noise `sigmas` {variant: sigma_body} (radians
    on the pose angles; `sigma_body_deg` in degrees), rows by increasing sigma."""
    order = sorted(sigmas, key=lambda variant: sigmas[variant])
    table = main_table(summaries, order, blank=False)
    table.insert(1, "sigma_body", [sigmas[v] for v in order])
    table.insert(2, "sigma_body_deg", [math.degrees(sigmas[v]) for v in order])
    return table


def regions_table(summaries: pd.DataFrame, variants: list[str]) -> pd.DataFrame:
    """Per variant and split (finest LOD, mean over subjects) the ground-truth metrics REGION_KEYS."""
    if not has_regions(summaries):
        raise ValueError(f"no summary holds the ground-truth region metrics ({', '.join(REGION_KEYS)}): only captures "
                         "with ground truth (a generated dataset such as synthetic) have them")
    rows = []
    for variant, part in finest_by_variant(summaries, variants):
        for split in SPLITS:
            rows_split = part[part["split"] == split]
            if not rows_split.empty:
                rows.append({"variant": variant, "split": split, **{key: rows_split[key].mean() for key in REGION_KEYS}})
    return pd.DataFrame(rows)


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
    return pd.DataFrame(rows).rename(columns=_metric_names(lpips, protocol_suffix(summaries)))


def read_train_log(path: Path) -> pd.DataFrame:
    """Training time and held-out PSNR of one train_log.csv, checked: numbers, both columns present. The time is
    `train_s` (held-out evaluations left out); logs older than that column give `wall_s` in its place. `probe_psnr`
    (pig.avatar.probe) comes along where the log has it."""
    columns = ["wall_s", "heldout_psnr"]
    try:
        log = pd.read_csv(path)
    except (OSError, UnicodeDecodeError, pd.errors.ParserError, pd.errors.EmptyDataError) as err:
        raise ValueError(f"{path}: not a readable train log ({err})") from None
    if not set(columns) <= set(log.columns):
        raise ValueError(f"{path}: train log lacks columns {sorted(set(columns) - set(log.columns))}; found {list(log.columns)}")
    try:
        parsed = log[columns].apply(pd.to_numeric)
        parsed["train_s"] = pd.to_numeric(log["train_s"]) if "train_s" in log.columns else parsed["wall_s"]
        if "probe_psnr" in log.columns:
            parsed["probe_psnr"] = pd.to_numeric(log["probe_psnr"])
        return parsed
    except (ValueError, TypeError) as err:
        raise ValueError(f"{path}: train log has a non-numeric wall_s, train_s, heldout_psnr or probe_psnr "
                         f"({err})") from None


def training_plot(logs: dict[str, dict[Path, pd.DataFrame]], path: Path, title: str) -> None:
    """Held-out PSNR against training wall time, one line per (variant, subject), from `read_train_log`: a colour
    per variant (distinct for up to 20), a line style per subject. A fit that probed (fit.probe_every) is drawn by
    its probes, many cheap points, and its full evaluations as unjoined squares; else by its full evaluations."""
    fig, ax = plt.subplots(figsize=(7, 4.5), dpi=120)
    colours = plt.get_cmap("tab10" if len(logs) <= 10 else "tab20")
    subjects = sorted({Path(file).parts[-3] for files in logs.values() for file in files})
    styles = ["-", "--", ":", "-."]
    probed = False
    for index, (variant, files) in enumerate(logs.items()):
        for file, log in files.items():
            subject = Path(file).parts[-3]
            colour = colours(index % colours.N)
            probes = log.dropna(subset=["probe_psnr"]) if "probe_psnr" in log.columns else log.iloc[:0]
            full = log.dropna(subset=["heldout_psnr"])
            probed = probed or len(probes) > 0
            line = probes if len(probes) else full
            ax.plot(line["train_s"], line["probe_psnr" if len(probes) else "heldout_psnr"], marker="o", markersize=3,
                    color=colour, linestyle=styles[subjects.index(subject) % len(styles)],
                    label=f"{variant} ({subject})")
            if len(probes):
                ax.plot(full["train_s"], full["heldout_psnr"], marker="s", markersize=5, linestyle="none", color=colour)
    ax.set_xlabel("training wall time, held-out evaluations left out [s]")
    ax.set_ylabel("held-out novel-view PSNR [dB]" + ("\nlines: probes over mask boxes; squares: whole frames" * probed))
    ax.set_title(title)
    ax.grid(alpha=0.3)
    if ax.get_lines():
        ax.legend(fontsize=8)
    fig.tight_layout()
    write_figure(path, fig)


def table_files(name: str, frame: pd.DataFrame, title: str) -> dict[str, str]:
    """{file name: text} of one table: `name`.csv at full precision (floats as their shortest repr, which reads
    back exactly), `name`.md and `name`.html (the report's page), both formatted from the CSV's text."""
    text = frame.to_csv(index=False)
    shown = read_table(io.StringIO(text)) if len(frame.columns) else frame  # a table without rows has no columns
    return {f"{name}.csv": text, f"{name}.md": to_markdown(shown, title), f"{name}.html": to_html(shown, title)}


def make_tables(dataset: str, summaries: list[Path], train_logs: list[Path], variants: list[str], output: Path,
                overwrite: bool = False) -> None:
    """The main tables: write the main and LOD tables and the training plot of `variants` to `output`, after every
    input has been read and checked; files of the same names are replaced only in a tables output folder, or
    with `overwrite`. The main table is the paper's Table 1 layout; region metrics are the regions table's."""
    safe_name(dataset, "dataset name", "--dataset")  # it names the files written into `output`
    table = read_summaries(summaries)
    main = main_table(table, variants, regions=False)
    lod = lod_table(table, variants)
    logs = {v: {p: read_train_log(p) for p in map(Path, train_logs) if p.parent.name == v} for v in variants}
    texts = {**table_files(dataset, main, f"{dataset}: novel views and novel poses (finest LOD)"),
             **table_files(f"{dataset}_lod", lod, f"{dataset}: levels of detail (novel views)")}
    plot = f"{dataset}_training.png"
    claim_files(output, [*texts, plot], "tables", [*summaries, *train_logs], overwrite)
    for name, text in texts.items():
        write_text(output / name, text)
    training_plot(logs, output / plot, f"{dataset}: held-out PSNR during training")
    print(texts[f"{dataset}.md"])
    print(texts[f"{dataset}_lod.md"])


def make_table(table: str, dataset: str, summaries: list[Path], variants: list[str], output: Path,
               sigmas: dict[str, float] | None = None, overwrite: bool = False) -> None:
    """One of the other tables (`ablation`, `noise`, `regions`) of `variants`, as `{dataset}_{table}.csv/.md/.html`
    in `output`, after every input has been read and checked; `sigmas` {variant: sigma_body} for `noise`."""
    safe_name(dataset, "dataset name", "--dataset")  # it names the files written into `output`
    summary = read_summaries(summaries)
    if table == "ablation":
        frame, title = main_table(summary, variants), f"{dataset}: structural ablation (finest LOD)"
    elif table == "noise":
        if sigmas is None or set(sigmas) != set(variants):
            raise ValueError(f"the noise table needs sigma_body of every variant {variants}, got {sigmas}")
        frame, title = noise_table(summary, sigmas), f"{dataset}: noisy body parameters (finest LOD)"
    elif table == "regions":
        frame, title = regions_table(summary, variants), f"{dataset}: ground-truth metrics per region (finest LOD)"
    else:
        raise ValueError(f"unknown table {table!r}; expected one of {[t for t in TABLES if t != 'main']}")
    texts = table_files(f"{dataset}_{table}", frame, title)
    claim_files(output, texts, "tables", summaries, overwrite)
    for name, text in texts.items():
        write_text(output / name, text)
    print(texts[f"{dataset}_{table}.md"])


def noise_sigmas(preset: str, variants: list[str]) -> dict[str, float]:
    """{variant: fit.sigma_body} of `variants` in `preset` (a name or a YAML path), overrides applied."""
    from pig.avatar.fit_config import FitConfig  # here: only the noise table needs it
    from pig.avatar.variants import variant_overrides
    from pig.config import load_preset, load_section

    data = load_preset(preset)
    return {v: load_section(data, "fit", FitConfig, variant_overrides(data, v).get("fit")).sigma_body for v in variants}


def main(argv: list[str] | None = None) -> int:
    parser = stage_parser("tables", __doc__, "pig tables --dataset synthetic --summaries "
                                             "results/synthetic/subject00/pig/metrics/novel_view_lod0.json --variants pig --output results/tables")
    parser.add_argument("--dataset", required=True, help="dataset name, the tables' file names (e.g. synthetic)")
    parser.add_argument("--table", choices=TABLES, default="main",
                        help="main: {dataset}.csv, _lod.csv and _training.png; else {dataset}_{table}.csv (default main)")
    parser.add_argument("--summaries", type=Path, nargs="+", required=True, help="metrics/{split}_lod{l}.json files")
    parser.add_argument("--train-logs", type=Path, nargs="*", default=[], help="{variant}/train_log.csv files (main table)")
    parser.add_argument("--variants", nargs="+", required=True, help="row order of the tables")
    add_preset_argument(parser, "the one the variants were fitted with: the noise table reads their fit.sigma_body")
    parser.add_argument("--output", type=Path, required=True, help="tables directory (results/tables)")
    add_common_arguments(parser)
    parser.add_argument("--overwrite", action="store_true",
                        help="replace files of the same names in an --output folder the tables stage did not write")
    args = parser.parse_args(argv)
    if args.table != "main" and args.train_logs:
        parser.error(f"--train-logs: only the main table plots training, not --table {args.table}")
    if args.table == "main":
        make_tables(args.dataset, args.summaries, args.train_logs, args.variants, args.output, args.overwrite)
    else:
        sigmas = noise_sigmas(args.preset, args.variants) if args.table == "noise" else None
        make_table(args.table, args.dataset, args.summaries, args.variants, args.output, sigmas, args.overwrite)
    return 0


if __name__ == "__main__":
    raise SystemExit(run_cli(main))

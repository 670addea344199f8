"""Result tables as papers print them: values rounded by column kind (PSNR 2 decimals, SSIM and LPIPS 3, FID 1,
splats as counts such as 12.5k), NaN written `n/a`, notes as numbered footnotes; as Markdown or a self-contained
HTML page (two header rows, a fixed first column). CSVs keep full precision: this module only formats them.

Column kinds come from the column names of pig.stages.tables (`novel_view_psnr`, `lpips_alex`,
`accuracy_mm_body`, ...), so every table (main, LOD, ablation, noise, regions) shares one formatter.
"""
from __future__ import annotations

import html
import math
import re
from dataclasses import dataclass
from decimal import ROUND_HALF_UP, Decimal, localcontext
from pathlib import Path

import pandas as pd

# Decimals per column kind; `splats` is a count, `text` is printed as is.
DECIMALS = {"psnr": 2, "ssim": 3, "lpips": 3, "fid": 1, "mm": 1, "mb": 2, "fps": 0, "deg": 1, "sigma": 3, "number": 3}
# Header labels of the metric kinds, with the direction that is better (as the paper's tables mark it).
LABELS = {"psnr": "PSNR↑", "ssim": "SSIM↑", "lpips": "LPIPS↓", "fid": "FID↓", "splats": "Splats", "mb": "MB↓",
          "fps": "FPS↑", "lod": "LOD", "variant": "Variant", "split": "Split", "device": "Device",
          "sigma_body": "σ body (rad)", "sigma_body_deg": "σ body (°)"}
MM_LABELS = {"accuracy": "accuracy (mm)↓", "completeness": "completeness (mm)↓", "drift": "drift (mm)↓"}
GROUPS = {"novel_view": "Novel views", "novel_pose": "Novel poses"}
REGIONS = {"garment", "body", "background"}  # pig.metrics.regions' masks
SUPERSCRIPT = str.maketrans("0123456789", "⁰¹²³⁴⁵⁶⁷⁸⁹")


def column_kind(name: str) -> str:
    """How a column's values are printed, from its name: a metric (`psnr`, `ssim`, `lpips`, `fid`), `splats`,
    `mm` (geometry error, drift), `mb`, `fps`, `sigma` / `deg` (noise level), `lod` / `variant` / ... (`text`)."""
    tokens = name.split("_")
    if name == "splats":
        return "splats"
    for kind in ("psnr", "ssim", "lpips", "fid"):
        if kind in tokens:
            return kind
    if "mm" in tokens:
        return "mm"
    if name in ("mb", "fps"):
        return name
    if name.startswith("sigma"):
        return "deg" if name.endswith("_deg") else "sigma"
    if name in LABELS:
        return "text"
    return "number"


def format_value(value, kind: str) -> str:
    """`value` as printed in a column of `kind`: decimals rounded half up on the value as written in the CSV (its
    shortest repr, so 0.9995 gives 1.000 as a reader rounding the CSV would), `n/a` for NaN or None, no `-0.00`."""
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "n/a"
    if kind == "text" or isinstance(value, str):
        return str(value)
    if math.isinf(value):
        return "inf" if value > 0 else "-inf"
    if kind == "splats":
        return format_count(value)
    step = Decimal(1).scaleb(-DECIMALS[kind])
    with localcontext(prec=400):  # enough digits for any float64 (1e308 at 3 decimals), the default 28 is not
        text = str(Decimal(repr(float(value))).quantize(step, rounding=ROUND_HALF_UP))
    return text[1:] if text.startswith("-") and not text.strip("-0.") else text


def format_count(value: float) -> str:
    """A count as the paper writes splats: 512, 12.5k, 100k, 1.25M (thousands to one decimal, millions to two)."""
    count = Decimal(repr(float(value)))
    for scale, suffix, digits in ((Decimal(10) ** 6, "M", 2), (Decimal(1000), "k", 1)):
        if abs(count) >= scale:
            text = str((count / scale).quantize(Decimal(1).scaleb(-digits), rounding=ROUND_HALF_UP))
            return text.rstrip("0").rstrip(".") + suffix
    return str(count.quantize(Decimal(1), rounding=ROUND_HALF_UP))


def column_header(name: str) -> tuple[str, str]:
    """(group, label) of a column: `novel_view_lpips_alex` -> ("Novel views", "LPIPS↓ (alex)"); a region column
    outside a split groups under its metric: `psnr_garment` -> ("PSNR↑", "garment"); group '' when none."""
    group = ""
    for split, title in GROUPS.items():
        if name.startswith(f"{split}_"):
            group, name = title, name[len(split) + 1:]
    if name in LABELS:
        return group, LABELS[name]
    kind = column_kind(name)
    tokens = name.split("_")
    if kind in ("psnr", "ssim", "lpips", "fid"):
        label, rest = LABELS[kind], [t for t in tokens if t != kind]
    elif kind == "mm":
        label, rest = MM_LABELS.get(tokens[0], f"{tokens[0]} (mm)"), [t for t in tokens[1:] if t != "mm"]
        if tokens[0] == "drift" and not group:  # drift_mm (mean over frames) beside drift_mm_last
            return label, " ".join(rest) + " frame" if rest else "mean"
    else:
        label, rest = name.replace("_", " "), []
    if rest and not group and set(rest) <= REGIONS:
        return label, " ".join(rest)
    return group, f"{label} ({' '.join(rest)})" if rest else label


@dataclass
class FormattedTable:
    """A table ready to print: `headers` (group, label) and `kinds` (column_kind) per column, `rows` of (text,
    footnote numbers) cells, and `notes`, the footnotes' texts (note k is `notes[k - 1]`)."""
    headers: list[tuple[str, str]]
    kinds: list[str]
    rows: list[list[tuple[str, list[int]]]]
    notes: list[str]


def format_table(table: pd.DataFrame) -> FormattedTable:
    """Formats a table of pig.stages.tables. Its `notes` column (texts joined by '; ') becomes footnotes marked on
    the row's first cell; a FID column's `_images` / `_biased` companions become a footnote on the FID cell.
    Footnotes are numbered in reading order (rows top down, cells left to right), one number per distinct text."""
    notes: dict[str, int] = {}

    def mark(text: str) -> int:
        return notes.setdefault(text, len(notes) + 1)

    fid_counts = [c for c in table.columns if f"{c}_images" in table and f"{c}_biased" in table]
    hidden = {"notes", *(f"{c}_{part}" for c in fid_counts for part in ("images", "biased"))}
    shown = [c for c in table.columns if c not in hidden]
    rows = []
    for _, record in table.iterrows():
        text = record["notes"] if "notes" in table else None
        row_notes = [n for n in text.split("; ") if n] if isinstance(text, str) else []
        cells = []
        for index, column in enumerate(shown):
            marks = [mark(n) for n in row_notes] if index == 0 else []
            value = record[column]
            if column in fid_counts and not pd.isna(value) and not pd.isna(record[f"{column}_images"]):
                biased = ", biased: fewer than the evaluate stage's fid_min_images" if record[f"{column}_biased"] else ""
                marks.append(mark(f"FID over {int(record[f'{column}_images'])} images per set{biased}"))
            cells.append((format_value(value, column_kind(column)), marks))
        rows.append(cells)
    return FormattedTable([column_header(c) for c in shown], [column_kind(c) for c in shown], rows, list(notes))


def _superscript(marks: list[int]) -> str:
    return ",".join(str(m) for m in marks).translate(SUPERSCRIPT).replace(",", "˒") if marks else ""


def _markdown_text(text: str) -> str:
    """`text` shown as is in Markdown: a `<` that would open an HTML tag and an `&` that would start an entity as
    entities (a plain `< 2000` stays readable), a `|` not ending a table cell (backslashes escaped first, so that one
    before it cannot undo its escape), a line break as a space."""
    text = str(text).replace("\\", "\\\\").replace("|", "\\|")
    text = re.sub(r"&(?=#?\w+;)", "&amp;", text)
    return " ".join(re.sub(r"<(?=[A-Za-z/!?])", "&lt;", text).splitlines())


def to_markdown(table: pd.DataFrame, title: str) -> str:
    """A GitHub Markdown table under `## title`: headers `group label` (e.g. `Novel views PSNR↑`), footnote
    markers as superscripts, the footnotes as a numbered list below. Texts are escaped (`_markdown_text`)."""
    formatted = format_table(table)
    headers = [_markdown_text(f"{group} {label}" if group else label) for group, label in formatted.headers]
    lines = [f"## {_markdown_text(title)}", "", "| " + " | ".join(headers) + " |", "|" + "---|" * len(headers)]
    lines += ["| " + " | ".join(_markdown_text(text) + _superscript(marks) for text, marks in row) + " |"
              for row in formatted.rows]
    if formatted.notes:
        lines += [""] + [f"{number}. {_markdown_text(note)}" for number, note in enumerate(formatted.notes, 1)]
    return "\n".join(lines) + "\n"


PAGE_STYLE = """
body { margin: 0; padding: 16px; font: 14px/1.4 system-ui, -apple-system, "Segoe UI", sans-serif; color: #1e293b; }
h1 { font-size: 16px; margin: 0 0 8px; }
div.scroll { overflow-x: auto; max-width: 100%; }
table { border-collapse: separate; border-spacing: 0; font-variant-numeric: tabular-nums; }
th, td { padding: 4px 10px; white-space: nowrap; border-bottom: 1px solid #e2e8f0; background: #fff; }
th { font-weight: 600; border-bottom: 1px solid #94a3b8; }
thead tr.groups th { border-bottom: 1px solid #cbd5e1; }
td.num { text-align: right; }
th.group + th.group, td.first-of-group, th.first-of-group { border-left: 1px solid #cbd5e1; }
th.first, td.first { position: sticky; left: 0; z-index: 1; text-align: left; border-right: 1px solid #94a3b8; }
tbody tr:hover td { background: #f1f5f9; }
sup { color: #64748b; }
ol.notes { color: #475569; margin: 12px 0 0; padding-left: 24px; max-width: 60em; }
"""


def to_html(table: pd.DataFrame, title: str) -> str:
    """A self-contained HTML page of the table: the column groups (novel views, novel poses) as a first header row,
    a fixed first column when the table scrolls sideways, numbers right-aligned, footnotes as a numbered list."""
    formatted = format_table(table)
    grouped = any(group for group, _ in formatted.headers)
    # Columns that open a group (or leave one) get a rule on their left.
    starts = {i for i in range(2, len(formatted.headers)) if formatted.headers[i - 1][0] != formatted.headers[i][0]}
    head = []
    if grouped:
        cells, index = [], 0
        while index < len(formatted.headers):
            group = formatted.headers[index][0]
            span = 1
            while index + span < len(formatted.headers) and group and formatted.headers[index + span][0] == group:
                span += 1
            if group:
                cells.append(f'<th class="group" colspan="{span}">{html.escape(group)}</th>')
            else:
                classes = " ".join(c for c in ("first" if index == 0 else "", "first-of-group" if index in starts else "") if c)
                cells.append(f'<th class="{classes}" rowspan="2">{html.escape(formatted.headers[index][1])}</th>')
            index += span
        head.append('<tr class="groups">' + "".join(cells) + "</tr>")
    labels = [f'<th class="{"first" if i == 0 else "first-of-group" if i in starts else ""}">{html.escape(label)}</th>'
              for i, (group, label) in enumerate(formatted.headers) if group or not grouped]
    head.append("<tr>" + "".join(labels) + "</tr>")
    body = []
    for row in formatted.rows:
        cells = []
        for i, (text, marks) in enumerate(row):
            classes = " ".join(c for c in ("first" if i == 0 else "", "num" if i and formatted.kinds[i] != "text" else "",
                                           "first-of-group" if i in starts else "") if c)
            sup = f"<sup>{','.join(map(str, marks))}</sup>" if marks else ""
            cells.append(f'<td class="{classes}">{html.escape(text)}{sup}</td>')
        body.append("<tr>" + "".join(cells) + "</tr>")
    notes = ("<ol class=\"notes\">" + "".join(f"<li>{html.escape(n)}</li>" for n in formatted.notes) + "</ol>"
             if formatted.notes else "")
    return (f'<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8"><title>{html.escape(title)}</title>'
            f"<style>{PAGE_STYLE}</style></head><body><h1>{html.escape(title)}</h1>"
            f'<div class="scroll"><table><thead>{"".join(head)}</thead><tbody>{"".join(body)}</tbody></table></div>'
            f"{notes}</body></html>\n")


def read_table(path: Path) -> pd.DataFrame:
    """A table CSV of the tables stage (floats read back exactly: pandas parses at round-trip precision); text
    columns stay text."""
    try:
        return pd.read_csv(path, keep_default_na=False,
                           na_values=[""], dtype={"variant": str, "lod": str, "split": str, "device": str, "notes": str})
    except (OSError, UnicodeDecodeError, pd.errors.ParserError, pd.errors.EmptyDataError) as err:
        raise ValueError(f"{path}: not a readable table CSV of the tables stage ({err})") from None

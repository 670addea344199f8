"""Tables as papers print them (pig.metrics.table_format): rounding per column kind against hand-worked values and
a bound on random ones, footnote numbering, the main table's Table 1 layout, CSVs read back at full precision, and
the HTML page's structure read by Python's own HTML parser."""
from __future__ import annotations

import csv
import html.parser
import json
import math
from decimal import Decimal
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from pig.metrics.table_format import column_header, column_kind, format_table, format_value, to_html, to_markdown
from pig.stages.tables import BLANK_ROW, REGION_KEYS, SPLITS, main_table, make_tables, read_summaries


@pytest.mark.parametrize("column, kind", [
    ("novel_view_psnr", "psnr"), ("psnr_garment", "psnr"), ("novel_pose_ssim_animatable_gaussians", "ssim"),
    ("novel_view_lpips_alex", "lpips"), ("lpips_vgg", "lpips"), ("novel_pose_fid", "fid"), ("splats", "splats"),
    ("accuracy_mm_body", "mm"), ("drift_mm_last", "mm"), ("mb", "mb"), ("fps", "fps"), ("sigma_body", "sigma"),
    ("sigma_body_deg", "deg"), ("variant", "text"), ("lod", "text"), ("device", "text"), ("other_value", "number"),
])
def test_column_kind_by_name(column, kind):
    assert column_kind(column) == kind


@pytest.mark.parametrize("value, kind, expected", [
    # Worked by hand: half up on the decimal value as the CSV writes it (0.9995 is the float nearest 0.9995,
    # 0.99949999999999994404..., which Python's own rounding sends down to 0.999).
    (0.9995, "ssim", "1.000"), (0.99949, "ssim", "0.999"), (0.0005, "lpips", "0.001"), (0.0235, "lpips", "0.024"),
    (27.125, "psnr", "27.13"), (27.134999, "psnr", "27.13"), (32.5, "psnr", "32.50"), (9.95, "fid", "10.0"),
    (109.72, "fid", "109.7"), (8.07, "fid", "8.1"), (42.44, "mm", "42.4"), (8.675, "mb", "8.68"), (241.5, "fps", "242"),
    (0.25, "sigma", "0.250"), (14.323944878, "deg", "14.3"),
    # Negative values round away from zero at a tie; a negative that rounds to zero prints without its sign.
    (-1.005, "psnr", "-1.01"), (-0.0004, "ssim", "0.000"), (-2.25, "fid", "-2.3"),
    (math.nan, "psnr", "n/a"), (None, "fid", "n/a"), (math.inf, "psnr", "inf"), (-math.inf, "psnr", "-inf"),
    # Splat counts as the paper writes them.
    (0, "splats", "0"), (999, "splats", "999"), (12500, "splats", "12.5k"), (25000, "splats", "25k"),
    (100000, "splats", "100k"), (16384, "splats", "16.4k"), (361000, "splats", "361k"), (1234567, "splats", "1.23M"),
    ("1/4", "text", "1/4"),
    # Past the decimal module's default 28 digits (a blown-up FID or drift): printed whole, not an error.
    (1e30, "fid", "1" + "0" * 30 + ".0"), (-2.5e25, "number", "-25" + "0" * 24 + ".000"),
])
def test_rounding_per_column_kind(value, kind, expected):
    assert format_value(value, kind) == expected


def test_rounding_stays_within_half_a_unit_of_the_last_place():
    rng = np.random.default_rng(0)
    for kind, decimals in (("psnr", 2), ("ssim", 3), ("lpips", 3), ("fid", 1)):
        for value in rng.uniform(-50, 250, 2000):
            text = format_value(float(value), kind)
            assert len(text.split(".")[1]) == decimals, text
            # Exact decimal arithmetic: |printed - value| <= half a unit of the last printed place.
            assert abs(Decimal(text) - Decimal(float(value))) <= Decimal(5) * Decimal(10) ** -(decimals + 1), (value, text)


def test_headers_name_group_metric_and_direction():
    assert column_header("novel_view_psnr") == ("Novel views", "PSNR↑")
    assert column_header("novel_pose_lpips_alex") == ("Novel poses", "LPIPS↓ (alex)")
    assert column_header("novel_view_ssim_animatable_gaussians") == ("Novel views", "SSIM↑ (animatable gaussians)")
    assert column_header("splats") == ("", "Splats")
    # The regions table groups its columns by metric.
    assert column_header("completeness_mm_garment") == ("completeness (mm)↓", "garment")
    assert column_header("ssim_background") == ("SSIM↑", "background")
    assert [column_header(c) for c in ("drift_mm", "drift_mm_last")] == [("drift (mm)↓", "mean"), ("drift (mm)↓", "last frame")]
    assert column_header("novel_pose_drift_mm_last") == ("Novel poses", "drift (mm)↓ (last)")


def _frame() -> pd.DataFrame:
    return pd.DataFrame({
        "variant": ["a", "b", BLANK_ROW],
        "novel_view_psnr": [30.0, 31.256, 18.0],
        "novel_view_fid": [12.34, math.nan, math.nan],
        "novel_view_fid_images": [36.0, math.nan, math.nan],
        "novel_view_fid_biased": [1.0, math.nan, math.nan],
        "splats": [100000, 12500, 0],
        "notes": ["LPIPS is NaN: no weights; fit without the LPIPS term", "fit without the LPIPS term", "black"],
    })


def test_footnotes_numbered_in_reading_order_one_number_per_text():
    formatted = format_table(_frame())
    assert formatted.notes == ["LPIPS is NaN: no weights", "fit without the LPIPS term",
                               "FID over 36 images per set, biased: fewer than the evaluate stage's fid_min_images",
                               "black"]
    assert [cell[1] for cell in formatted.rows[0]] == [[1, 2], [], [3], []]
    assert [cell[1] for cell in formatted.rows[1]] == [[2], [], [], []]  # the shared note keeps its number
    assert formatted.rows[2][0] == (BLANK_ROW, [4])
    assert [cell[0] for cell in formatted.rows[1]] == ["b", "31.26", "n/a", "12.5k"]
    markdown = to_markdown(_frame(), "t")
    assert "| Variant | Novel views PSNR↑ | Novel views FID↓ | Splats |" in markdown
    assert "| a¹˒² | 30.00 | 12.3³ | 100k |" in markdown and "| b² | 31.26 | n/a | 12.5k |" in markdown
    assert markdown.endswith("\n1. LPIPS is NaN: no weights\n2. fit without the LPIPS term\n"
                             "3. FID over 36 images per set, biased: fewer than the evaluate stage's fid_min_images\n"
                             "4. black\n")
    assert "notes" not in markdown and "fid_images" not in markdown


class _Cells(html.parser.HTMLParser):
    """Rows of (tag, attributes, text) cells, and the footnotes' texts, of a page."""

    def __init__(self):
        super().__init__()
        self.rows, self.notes, self._cell, self._in_li = [], [], None, False

    def handle_starttag(self, tag, attrs):
        if tag == "tr":
            self.rows.append([])
        elif tag in ("td", "th"):
            self._cell = [tag, dict(attrs), ""]
        elif tag == "li":
            self._in_li = True
            self.notes.append("")

    def handle_endtag(self, tag):
        if tag in ("td", "th"):
            self.rows[-1].append(tuple(self._cell))
            self._cell = None
        elif tag == "li":
            self._in_li = False

    def handle_data(self, data):
        if self._cell is not None:
            self._cell[2] += data
        elif self._in_li:
            self.notes[-1] += data


def test_html_page_has_group_headers_a_fixed_first_column_and_the_footnotes():
    page = _Cells()
    page.feed(to_html(_frame(), "a <title>"))
    groups, labels, *body = page.rows
    assert [(tag, attrs.get("colspan"), attrs.get("rowspan"), text) for tag, attrs, text in groups] == [
        ("th", None, "2", "Variant"), ("th", "2", None, "Novel views"), ("th", None, "2", "Splats")]
    assert [text for _, _, text in labels] == ["PSNR↑", "FID↓"]
    assert [[text for _, _, text in row] for row in body] == [["a1,2", "30.00", "12.33", "100k"],
                                                               ["b2", "31.26", "n/a", "12.5k"],
                                                               [f"{BLANK_ROW}4", "18.00", "n/a", "0"]]
    assert all("first" in row[0][1]["class"].split() for row in body)
    assert page.notes == format_table(_frame()).notes
    assert "a &lt;title&gt;" in to_html(_frame(), "a <title>")


def _summaries(root: Path, rng) -> list[Path]:
    paths = []
    for subject in ("s0", "s1"):
        for split in SPLITS:
            for lod in range(2):
                path = root / "synthetic" / subject / "pig" / "metrics" / f"{split}_lod{lod}.json"
                path.parent.mkdir(parents=True, exist_ok=True)
                data = {"split": split, "lod": lod, "lpips_net": "alex", "splats": 1000 * 2 ** lod, "model_mb": 1.0,
                        "fps": 10.0, "device": "cpu", "psnr_blank": 10.0 + rng.uniform(), "ssim_blank": rng.uniform(),
                        "fid": rng.uniform(5, 200), "fid_images": 40, "fid_min_images": 2000}
                data.update({key: float(rng.uniform(0.01, 40)) for key in ("psnr", "ssim", "lpips", *REGION_KEYS)})
                path.write_text(json.dumps(data))
                paths.append(path)
    return paths


def test_main_table_is_table_1_and_its_csv_reads_back_at_full_precision(tmp_path):
    paths = _summaries(tmp_path, np.random.default_rng(3))
    out = tmp_path / "tables"
    make_tables("synthetic", paths, [], ["pig"], out)
    with open(out / "synthetic.csv", newline="") as handle:  # the standard library's reader: no pandas in between
        rows = list(csv.DictReader(handle))
    metrics = [f"{split}_{m}" for split in SPLITS for m in ("psnr", "ssim", "lpips_alex", "fid")]
    assert list(rows[0]) == ["variant", *[c for split in SPLITS for c in (
        f"{split}_psnr", f"{split}_ssim", f"{split}_lpips_alex", f"{split}_fid", f"{split}_fid_images",
        f"{split}_fid_biased")], "splats", "notes"]
    expected = main_table(read_summaries(paths), ["pig"]).set_index("variant")
    for row in rows:
        for column in metrics:
            if row[column]:
                assert float(row[column]) == expected.loc[row["variant"], column], column  # exact, not approximate
    # The means themselves, in float64 from the summaries.
    records = [json.loads(p.read_text()) for p in paths]
    for split in SPLITS:
        psnr = np.mean([r["psnr"] for r in records if r["split"] == split and r["lod"] == 1])
        assert float(rows[0][f"{split}_psnr"]) == pytest.approx(psnr, rel=1e-15)
    markdown = (out / "synthetic.md").read_text()
    assert markdown.splitlines()[2] == ("| Variant | Novel views PSNR↑ | Novel views SSIM↑ | Novel views LPIPS↓ (alex) | "
                                        "Novel views FID↓ | Novel poses PSNR↑ | Novel poses SSIM↑ | "
                                        "Novel poses LPIPS↓ (alex) | Novel poses FID↓ | Splats |")
    pig = expected.loc["pig"]
    assert f"| pig | {format_value(pig['novel_view_psnr'], 'psnr')} | " in markdown and "| 2k |" in markdown
    assert (out / "synthetic.html").read_text().count("<tr>") == 1 + 2  # header labels, pig, blank
    # The region metrics are the regions table's alone.
    assert not [c for c in rows[0] if any(key in c for key in REGION_KEYS)]


def test_default_target_builds_the_regions_table_and_the_reports_turntable(tmp_path):
    """The region metrics left the main table: the default target of a dataset with ground truth builds the regions
    table, and the report's short turntable (the animate rule's `preview` clip)."""
    from test_tables import _synthetic_workdir
    from test_workflow import job_counts, snakemake_run

    work = _synthetic_workdir(tmp_path)
    output = snakemake_run(work, "--dry-run", "--printshellcmds", "--config", "preset=config/test preset.yaml")
    assert job_counts(output) == {"generate_capture": 1, "preprocess_capture": 1, "fit_avatar": 1, "render_split": 2,
                                  "evaluate": 4, "make_tables": 1, "make_table": 1, "montage_split": 2, "animate": 1,
                                  "all": 1}
    commands = [line for line in output.splitlines() if "python -m pig " in line]
    assert any("python -m pig tables --table regions " in line for line in commands)
    animate = next(line for line in commands if "python -m pig animate " in line)
    assert "--output results/synthetic/subject00/pig/animate/preview --page " in animate
    assert "--seconds 2.5 --orbit-period 2.5 --size 160 160" in animate and "--motion" not in animate


def test_markdown_shows_texts_as_they_are_in_their_own_cells():
    """Sweep three: a `|` in a variant name split its cell, shifting that row's values under the wrong headers,
    and HTML in a name or note was rendered as HTML. Read back by markdown-it (CommonMark with GitHub's tables,
    raw HTML allowed as GitHub allows it), every cell holds its text and nothing became a tag."""
    markdown_it = pytest.importorskip("markdown_it")
    frame = _frame()
    names = ["a|b", "<img src=x onerror=alert(1)>", "c\\|d &amp; <b>e</b>"]
    frame["variant"] = names
    frame["notes"] = ["<script>alert(1)</script>", "x|y (< 2000)", "black"]
    markdown = to_markdown(frame, "t <i>|</i>")
    assert "x\\|y (< 2000)" in markdown  # a `<` that opens no tag stays as it is
    rendered = markdown_it.MarkdownIt("commonmark", {"html": True}).enable("table").render(markdown)
    page = _Cells()
    page.feed(rendered)
    header, *rows = page.rows
    assert [text for _, _, text in header] == ["Variant", "Novel views PSNR↑", "Novel views FID↓", "Splats"]
    assert [[text for _, _, text in row] for row in rows] == [
        [f"{names[0]}¹", "30.00", "12.3²", "100k"], [f"{names[1]}³", "31.26", "n/a", "12.5k"],
        [f"{names[2]}⁴", "18.00", "n/a", "0"]]
    assert page.notes == ["<script>alert(1)</script>", "FID over 36 images per set, biased: fewer than the evaluate "
                          "stage's fid_min_images", "x|y (< 2000)", "black"]
    assert "<script" not in rendered and "<img" not in rendered and "<b>" not in rendered and "<i>" not in rendered
    assert "<h2>t &lt;i&gt;|&lt;/i&gt;</h2>" in rendered

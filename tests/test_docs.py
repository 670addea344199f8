"""The README as a landing page and the user guide under docs/: what they state is checked against the repository.

The README's first screen (60 lines) holds the picture, the two fresh-machine commands (the test one exactly as
`.ci/run` runs it) and the default run's result table, whose header and cells must be the main table's
(`docs/default_run_synthetic.csv`, that run's CSV) rounded as papers print; every relative link of README.md and
docs/*.md reaches an existing file and, for a Markdown file, an existing heading; every repository path and
`pig.*` name in their code spans exists.
"""
from __future__ import annotations

import argparse
import ast
import csv
import glob
import importlib
import math
import re
import tomllib
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
README = REPO / "README.md"
PAGES = [README, *sorted((REPO / "docs").glob("*.md"))]
FIRST_SCREEN = 60
VENV = "python3 -m venv .venv && . .venv/bin/activate"
DEFAULT_RUN_CSV = REPO / "docs" / "default_run_synthetic.csv"
# The paper's Table 1: per split PSNR, SSIM, LPIPS, FID (LPIPS named with its backbone, as the tables stage does).
PAPER_METRIC = re.compile(r"^(novel_view|novel_pose)_(psnr|ssim|lpips_[a-z]+|fid)$")
DECIMALS = {"psnr": 2, "ssim": 3, "lpips": 3, "fid": 1}
FOOTNOTE_MARKS = "¹²³⁴⁵⁶⁷⁸⁹⁰˒"  # superscript numbers, joined by ˒ as the tables stage marks notes


def first_screen() -> list[str]:
    return README.read_text(encoding="utf-8").splitlines()[:FIRST_SCREEN]


def code_blocks(lines: list[str]) -> list[list[str]]:
    """Indented (4-space) code blocks, each a list of its lines without the indent."""
    blocks, current = [], []
    for line in lines:
        if line.startswith("    ") and line.strip():
            current.append(line[4:].rstrip())
        elif current and not line.strip():
            continue
        elif current:
            blocks.append(current)
            current = []
    return blocks + ([current] if current else [])


def table_rows(lines: list[str]) -> list[list[str]]:
    """The first Markdown table among `lines`: header, then data rows (the separator row dropped)."""
    rows = [line for line in lines if line.startswith("|")]
    assert len(rows) >= 3, "expected a Markdown table (header, separator, rows) in the README's first screen"
    cells = [[cell.strip() for cell in row.strip().strip("|").split("|")] for row in rows]
    assert set("".join(cells[1])) <= set("-: "), f"expected a separator row under the header, found {cells[1]}"
    return [cells[0], *cells[2:]]


def column_key(header: str) -> str:
    """`Novel views LPIPS↓ (alex)` -> `novel_view_lpips_alex`: the CSV column a README header cell names."""
    words = re.sub(r"[↑↓()]", " ", header).lower().split()
    return "_".join(word.removesuffix("s") if word in ("views", "poses") else word for word in words)


def without_marks(cell: str) -> str:
    return cell.rstrip(FOOTNOTE_MARKS + " ")


def paper_format(column: str, value: str) -> str:
    """A CSV value as papers print it: PSNR 2 decimals, SSIM and LPIPS 3, FID 1; empty or NaN is `n/a`."""
    if value == "" or math.isnan(float(value)):
        return "n/a"
    kind = column.split("_")[2]
    return f"{float(value):.{DECIMALS[kind]}f}"


def splat_count(cell: str) -> int:
    """`16k`, `16,000` or `16000` as a count."""
    text = cell.replace(",", "")
    return int(float(text[:-1]) * 1000) if text.endswith("k") else int(text)


def test_first_screen_shows_the_picture():
    images = [m.group(1) for line in first_screen() for m in re.finditer(r"!\[[^\]]*\]\(([^)\s]+)\)", line)]
    assert images, "expected a picture (![...](docs/....png)) in the README's first 60 lines"
    path = REPO / images[0]
    assert path.is_file(), f"{images[0]}: the README's picture does not exist"
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", f"{images[0]}: expected a PNG file"


def test_first_screen_has_both_commands_with_the_venv_step_and_python_version():
    head = first_screen()
    blocks = [block for block in code_blocks(head) if block[0] == VENV]
    assert len(blocks) == 2, f"expected two commands starting with the venv step `{VENV}`, found {len(blocks)}"
    run, test = (block[1:] for block in blocks)
    assert len(run) == 1 and "snakemake --cores 2" in run[0] and run[0].startswith("pip install torch=="), run
    assert len(test) == 1 and "python -m pytest" in test[0] and test[0].startswith("pip install torch=="), test
    # One torch pin for both commands.
    assert run[0].split()[2] == test[0].split()[2]
    required = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["requires-python"]
    version = required.removeprefix(">=")
    assert f"Python {version} or newer" in "\n".join(head), f"expected the README to state Python {version} or newer"


def test_ci_runs_exactly_the_readmes_test_command():
    tests = [block[1] for block in code_blocks(first_screen()) if block[0] == VENV and "pytest" in block[1]]
    assert tests, "expected the README's test command (after the venv step) in its first 60 lines"
    test = tests[0]
    commands = [line.strip() for line in (REPO / ".ci" / "run").read_text().splitlines()
                if line.strip() and not line.lstrip().startswith("#")]
    assert [line for line in commands if line.removesuffix(" || exit") == test], (
        f"expected .ci/run to run the README's test command `{test}` as one line")
    # Nothing else in .ci/run runs the tests or installs the package in another way.
    assert [line for line in commands if "pytest" in line or "-e '.[" in line] == [f"{test} || exit"]


def test_first_screen_table_is_the_default_runs_main_table():
    header, *rows = table_rows(first_screen())
    with DEFAULT_RUN_CSV.open(newline="", encoding="utf-8") as f:
        table = list(csv.DictReader(f))
    columns = list(table[0])
    paper_columns = [c for c in columns if PAPER_METRIC.match(c)]
    keys = [column_key(cell) for cell in header]
    # The paper's Table 1 as the main table has it: variant, novel view x 4, novel pose x 4, splats.
    assert keys == ["variant", *paper_columns, "splats"], keys
    assert len(paper_columns) == 8 and paper_columns[0] == "novel_view_psnr" and paper_columns[4] == "novel_pose_psnr"
    by_variant = {row["variant"]: row for row in table}
    assert [without_marks(row[0]) for row in rows] == [row["variant"] for row in table]
    for row in rows:
        source = by_variant[without_marks(row[0])]
        for key, cell in zip(keys[1:-1], row[1:-1]):
            assert without_marks(cell) == paper_format(key, source[key]), (row[0], key, cell, source[key])
        assert splat_count(without_marks(row[-1])) == int(float(source["splats"]))


def github_slug(heading: str) -> str:
    """GitHub's anchor for a heading: inline code and links reduced to their text, lowercase, punctuation dropped,
    spaces to hyphens."""
    text = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", heading).replace("`", "").strip().lower()
    return re.sub(r"[^\w\- ]", "", text).replace(" ", "-")


def anchors(page: Path) -> set[str]:
    """Every heading's anchor in `page` (repeats numbered -1, -2, ... as GitHub does), outside fenced code."""
    seen: dict[str, int] = {}
    found = set()
    fenced = False
    for line in page.read_text(encoding="utf-8").splitlines():
        if line.startswith("```"):
            fenced = not fenced
        match = None if fenced else re.match(r"^#{1,6}\s+(.*?)\s*#*\s*$", line)
        if match:
            slug = github_slug(match.group(1))
            count = seen.get(slug, 0)
            found.add(slug if count == 0 else f"{slug}-{count}")
            seen[slug] = count + 1
    return found


def prose(page: Path) -> str:
    """The page without its code: fenced blocks, indented (4-space) code lines and inline code spans."""
    text = re.sub(r"^```.*?^```", "", page.read_text(encoding="utf-8"), flags=re.M | re.S)
    text = "\n".join(line for line in text.splitlines() if not line.startswith("    "))
    return re.sub(r"`[^`]*`", "", text)


def links(page: Path) -> list[str]:
    return re.findall(r"!?\[[^\]]*\]\(([^)\s]+)\)", prose(page))


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(REPO)))
def test_relative_links_reach_files_and_headings(page):
    problems = []
    for target in links(page):
        if re.match(r"^[a-z][a-z0-9+.-]*:", target):  # http:, https:, mailto:
            continue
        path, _, anchor = target.partition("#")
        resolved = (page.parent / path).resolve() if path else page
        if not resolved.is_relative_to(REPO):
            problems.append(f"{target}: outside the repository")
        elif not resolved.exists():
            problems.append(f"{target}: no such file")
        elif anchor and resolved.suffix == ".md" and anchor not in anchors(resolved):
            problems.append(f"{target}: no heading with anchor #{anchor} in {resolved.relative_to(REPO)}")
    assert not problems, f"{page.relative_to(REPO)}: " + "; ".join(problems)


def code_spans(page: Path) -> list[str]:
    text = re.sub(r"^```.*?^```", "", page.read_text(encoding="utf-8"), flags=re.M | re.S)
    return re.findall(r"`([^`\n]+)`", text)


REPO_PATH = re.compile(r"^(?:\.\./)?((?:benchmarks|config|docs|envs|pig|tests|workflow)/[\w./*-]*)$")
PIG_NAME = re.compile(r"^pig(?:\.\w+)+$")
PLACEHOLDER = re.compile(r"\.[A-Z]+(\.|$)")  # pig.stages.STAGE: a stand-in, not a name


def top_level_names(source: Path) -> set[str]:
    tree = ast.parse(source.read_text(encoding="utf-8"))
    names = set()
    for node in tree.body:
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            names.add(node.name)
        elif isinstance(node, (ast.Assign, ast.AnnAssign)):
            targets = node.targets if isinstance(node, ast.Assign) else [node.target]
            names.update(t.id for t in targets if isinstance(t, ast.Name))
    return names


def pig_name_exists(name: str) -> bool:
    """`pig.a.b` a module (file or package) of this checkout, or `pig.a.B` a top-level name of module `pig.a`;
    read from the source, nothing imported."""
    parts = name.split(".")
    for split in range(len(parts), 0, -1):
        base = REPO.joinpath(*parts[:split])
        module = base / "__init__.py" if base.is_dir() else base.with_suffix(".py")
        if module.is_file():
            rest = parts[split:]
            return not rest or (len(rest) == 1 and rest[0] in top_level_names(module))
    return False


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(REPO)))
def test_named_paths_and_modules_exist(page):
    missing = []
    for span in code_spans(page):
        for word in span.split():
            word = word.rstrip(",;:")
            path = REPO_PATH.match(word)
            if path and "{" not in word and not glob.glob(str(REPO / path.group(1))):
                missing.append(word)
            if PIG_NAME.match(word) and not PLACEHOLDER.search(word) and not pig_name_exists(word):
                missing.append(word)
    assert not missing, f"{page.relative_to(REPO)} names what the repository does not have: {missing}"


def commands(page: Path) -> list[list[str]]:
    """The command lines in a page's code (spans and indented blocks; a block's indented or `\\`-ended lines
    continue the line above), split at `&&`, ` | ` and `;`, each as its words."""
    text = re.sub(r"^```.*?^```", "", page.read_text(encoding="utf-8"), flags=re.M | re.S)
    lines = text.splitlines()
    code = [span.replace("\n", " ") for span in re.findall(r"`([^`]+)`", prose_without_blocks(lines))]
    for block in code_blocks(lines):
        code.append(re.sub(r"\\?\n(?=\s)|\\\n", " ", "\n".join(block)))
    # A pipe between spaces separates commands; one inside a word is a choice (`--device auto|cpu`).
    return [part.split() for chunk in code for part in re.split(r"&&|\s\|\|?\s|;|\n", chunk)]


def prose_without_blocks(lines: list[str]) -> str:
    return "\n".join(line for line in lines if not line.startswith("    "))


class _Parsed(Exception):
    """Raised in place of parsing: carries the stage's parser out of its `main`."""

    def __init__(self, parser: argparse.ArgumentParser):
        super().__init__(parser.prog)
        self.parser = parser


def stage_options(stage: str, monkeypatch) -> set[str]:
    """The option strings `pig STAGE` accepts, from the parser its `main` builds (nothing runs past parsing)."""
    module = importlib.import_module(f"pig.stages.{stage}")

    def capture(self, *args, **kwargs):
        raise _Parsed(self)

    with monkeypatch.context() as patch:
        patch.setattr(argparse.ArgumentParser, "parse_args", capture)
        with pytest.raises(_Parsed) as parsed:
            module.main([])
    return {option for action in parsed.value.parser._actions for option in action.option_strings}


def test_documented_stage_options_exist(monkeypatch):
    """Every `pig STAGE --option` written in README.md or docs/ is an option of that stage (the stages of this
    checkout's `pig` command; pig.cli.STAGES)."""
    from pig.cli import STAGES

    used: dict[str, dict[str, set[str]]] = {}
    for page in PAGES:
        for words in commands(page):
            for index, word in enumerate(words[:-1]):
                if word == "pig" and words[index + 1] in STAGES:
                    options = {m for w in words[index + 2:] for m in re.findall(r"(?<![\w-])--[a-z][a-z0-9-]*", w)}
                    used.setdefault(words[index + 1], {}).setdefault(str(page.relative_to(REPO)), set()).update(options)
    assert {"fit", "render", "evaluate", "view", "animate", "export"} <= used.keys(), sorted(used)
    unknown = {}
    for stage, pages in sorted(used.items()):
        accepted = stage_options(stage, monkeypatch)
        for page, options in pages.items():
            if options - accepted:
                unknown[f"{page}: pig {stage}"] = sorted(options - accepted)
    assert not unknown, f"options that the stages do not have: {unknown}"


def test_checks_find_what_is_wrong(tmp_path, monkeypatch):
    """The checkers themselves: a dead link, a missing anchor, a missing path and module are reported."""
    page = tmp_path / "page.md"
    page.write_text("# A heading: `with code`\n\n[ok](#a-heading-with-code) [dead](nowhere.md) [bad](#none)\n"
                    "`pig/no_such_module.py` `pig.config.no_such_name` `pig.config.load_yaml`\n", encoding="utf-8")
    assert anchors(page) == {"a-heading-with-code"}
    assert links(page) == ["#a-heading-with-code", "nowhere.md", "#none"]
    assert not (tmp_path / "nowhere.md").exists()
    assert pig_name_exists("pig.config.load_yaml") and pig_name_exists("pig.data.render_store.RenderReader")
    assert not pig_name_exists("pig.config.no_such_name") and not pig_name_exists("pig.no_such_module")
    assert github_slug("Bit-identical CPU fits: the kernel that raced, and its fix (CPU, 2026-11-25)") == (
        "bit-identical-cpu-fits-the-kernel-that-raced-and-its-fix-cpu-2026-11-25")
    page.write_text("Run `pig fit --capture C\n--output O --device cpu|cuda --no-such-flag` and:\n\n"
                    "    pig montage --views 3 \\\n        --split x && pig tables --dataset d | tee log\n", encoding="utf-8")
    assert [w for w in commands(page) if w[:1] == ["pig"]] == [
        ["pig", "fit", "--capture", "C", "--output", "O", "--device", "cpu|cuda", "--no-such-flag"],
        ["pig", "montage", "--views", "3", "--split", "x"], ["pig", "tables", "--dataset", "d"]]
    assert {"--capture", "--output", "--preset"} <= stage_options("fit", monkeypatch)
    assert "--no-such-flag" not in stage_options("fit", monkeypatch)

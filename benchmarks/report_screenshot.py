"""Screenshot of a Snakemake report's item as a reader sees it (headless Chromium, the menu clicked as in
tests/test_report.py), and how long the default target's turntable for the report takes to render.

    python benchmarks/report_screenshot.py --report report.html --output docs/report_tables.png
    python benchmarks/report_screenshot.py --turntable results/synthetic/subject00/pig/avatar.pt --preset cpu-demo

docs/report_tables.png is the first command on the report of a cpu-demo default run (benchmarks/NOTES.md).
"""
from __future__ import annotations

import argparse
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2

REPO = Path(__file__).resolve().parent.parent
sys.path[:0] = [str(REPO), str(REPO / "tests")]  # this checkout's package and its report test's helper


def screenshot(report: Path, output: Path, category: str, label: str, filename: str, width: int, height: int) -> None:
    from test_report import open_item

    from pig.viewer.browser import HeadlessChromium

    with HeadlessChromium(width, height) as browser:
        browser.goto(report.resolve().as_uri())
        open_item(browser, category, label, filename)
        time.sleep(0.5)  # fonts settle
        cv2.imwrite(str(output), browser.screenshot()[..., ::-1], [cv2.IMWRITE_PNG_COMPRESSION, 9])
    print(f"{output}: {category} / {label} at {width} x {height}")


def turntable_seconds(checkpoint: Path, preset: str, repeats: int) -> None:
    """Wall time of `pig animate` with the preview clip's options (workflow/rules/common.smk), start to end."""
    options = next(line.split("=", 1)[1].strip().strip('"') for line in
                   (REPO / "workflow" / "rules" / "common.smk").read_text().splitlines() if line.startswith("PREVIEW_OPTIONS"))
    print("| run | wall s | CPU s (user + sys) | load average (1 min) |\n|---|---|---|---|")
    for run in range(repeats):
        with tempfile.TemporaryDirectory() as tmp:
            load, cpu_before, start = os.getloadavg()[0], _children_cpu(), time.perf_counter()
            subprocess.run([sys.executable, "-m", "pig", "animate", "--checkpoint", str(checkpoint), "--output",
                            f"{tmp}/preview", "--page", f"{tmp}/preview.html", "--preset", preset, "--quiet",
                            *options.split()], check=True, capture_output=True)
            wall, cpu = time.perf_counter() - start, _children_cpu() - cpu_before
            print(f"| {run} | {wall:.1f} | {cpu:.1f} | {load:.1f} |")
    print(f"options: {options}")


def _children_cpu() -> float:
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--report", type=Path, help="report.html of `snakemake --report`")
    parser.add_argument("--output", type=Path, default=Path("report_tables.png"))
    parser.add_argument("--item", nargs=3, default=["Tables", "main", "synthetic.html"],
                        metavar=("CATEGORY", "LABEL", "FILENAME"), help="the item to open (default: the main table)")
    parser.add_argument("--size", type=int, nargs=2, default=[1400, 700], metavar=("WIDTH", "HEIGHT"))
    parser.add_argument("--turntable", type=Path, help="avatar.pt: time the report's turntable instead")
    parser.add_argument("--preset", default="cpu-demo")
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    if args.turntable:
        turntable_seconds(args.turntable, args.preset, args.repeats)
    elif args.report:
        screenshot(args.report, args.output, *args.item, *args.size)
    else:
        parser.error("give --report or --turntable")


if __name__ == "__main__":
    main()

"""The Snakemake report (`snakemake --report`) as a reader sees it: built by Snakemake at the test preset from
hand-written evaluate summaries and a tiny fitted avatar (the tables, the regions table and the report's turntable
run for real), then opened in a real headless Chromium at 1400 x 900. The report is a React app: an item opens in
its main pane (an iframe) when its eye button is clicked, so the test clicks through the menu as a reader would and
reads the iframe's rendered layout.

Needs Debian's chromium (`.ci/run` installs it where it runs as root); skips and says why where it is missing.
"""
from __future__ import annotations

import importlib.util
import json
import shutil
import time
from pathlib import Path

import pytest

from pig.viewer.browser import find_chromium

REPO = Path(__file__).resolve().parent.parent
WIDTH, HEIGHT = 1400, 900
RUN = Path("results/synthetic/subject00/pig")
TARGETS = ["results/tables/synthetic.csv", "results/tables/synthetic_regions.csv", str(RUN / "animate/preview.html")]


def _skip_reason() -> str | None:
    if importlib.util.find_spec("websockets") is None:
        return "websockets is not installed (pip install -e '.[viewer]')"
    if find_chromium() is None:
        return "Chromium is not installed (Debian: apt-get install chromium; .ci/run installs it as root)"
    return None


def open_item(browser, category: str, label: str, filename: str) -> None:
    """Click `category` in the report's menu, then the eye button of the item whose row shows `label`, and wait
    until the main pane's iframe has loaded the item (`filename`)."""
    # The menu lists the categories; from inside one, its breadcrumb "Results" leads back to them.
    click_category = (f"(() => {{ const links = Array.from(document.querySelectorAll('nav a')); const a = links.find(x => "
                      f"x.textContent.trim() === {json.dumps(category)} && !x.closest('ol')); if (a) {{ a.click(); "
                      "return true; } const up = links.find(x => x.textContent.trim() === 'Results'); if (up) up.click(); "
                      "return false; })()")
    click_eye = (f"(() => {{ const row = Array.from(document.querySelectorAll('nav tbody tr')).find(r => "
                 f"Array.from(r.cells).some(c => c.textContent.trim() === {json.dumps(label)})); if (!row) return false; "
                 "row.querySelector('a[iconname=eye]').click(); return true; })()")
    browser.wait_for("document.querySelector('nav') !== null")
    browser.wait_for(click_category, timeout_s=10)
    browser.wait_for(click_eye, timeout_s=10)
    browser.wait_for(f"(() => {{ const f = document.querySelector('iframe'); return f !== null && "
                     f"f.src.includes({json.dumps(f'filename={filename};')}); }})()", timeout_s=10)
    # The frame's document must be the item's own: until its navigation commits, the frame still holds the item
    # shown before, complete too (the race that once made the preview's video read as missing).
    loaded = (f"document.URL.includes({json.dumps(f'filename={filename};')}) && document.readyState === 'complete' "
              "&& document.body !== null")
    end = time.monotonic() + 10
    while time.monotonic() < end:
        try:
            if browser.evaluate_in_frame(loaded):
                return
        except RuntimeError:  # the frame is not there yet
            pass
        time.sleep(0.05)
    raise TimeoutError(f"report item {label!r} did not load")


TABLE_LAYOUT = """(() => {
    const box = document.querySelector('div.scroll'), table = box.querySelector('table');
    const rows = Array.from(table.rows), last = rows[rows.length - 1].cells;
    const lastCell = last[last.length - 1].getBoundingClientRect();
    const header = rows[0].cells[rows[0].cells.length - 1].getBoundingClientRect();
    return {scrollWidth: box.scrollWidth, clientWidth: box.clientWidth, viewport: window.innerWidth,
            lastRight: Math.max(lastCell.right, header.right), lastWidth: lastCell.width,
            lastText: last[last.length - 1].textContent, rows: rows.length};
})()"""


@pytest.fixture(scope="module")
def report(tmp_path_factory, request) -> Path:
    """report.html of the test preset's tables, regions table, loss curve and turntable."""
    reason = _skip_reason()
    if reason:
        pytest.skip(reason)
    from test_tables import _summary
    from test_workflow import snakemake_run

    _, checkpoint = request.getfixturevalue("tiny_fit")
    work = tmp_path_factory.mktemp("report") / "work dir"
    work.mkdir()
    shutil.copytree(REPO / "config", work / "config")
    shutil.copyfile(REPO / "config" / "presets" / "test.yaml", work / "config" / "test preset.yaml")
    (work / RUN).mkdir(parents=True)
    for name in ("avatar.pt", "train_log.csv", "train_log.png"):  # the fit's outputs, in place
        shutil.copyfile(checkpoint.parent / name, work / RUN / name)
    for split in ("novel_view", "novel_pose"):
        for lod in range(2):
            _summary(work / "results", "subject00", "pig", split, lod)
    settings = ["--config", "preset=config/test preset.yaml", "variants=[pig]"]
    snakemake_run(work, *TARGETS, "--cores", "2", "--allowed-rules", "make_tables", "make_table", "animate", *settings)
    snakemake_run(work, *TARGETS, "--report", "report.html", *settings)
    return work / "report.html"


def test_report_shows_the_main_table_whole_and_the_turntable_at_1400_px(report):
    from pig.viewer.browser import HeadlessChromium

    results = report.read_text()
    for item in ("results/tables/synthetic.html", "results/tables/synthetic_lod.html",
                 "results/tables/synthetic_regions.html", "results/tables/synthetic_training.png",
                 f"{RUN}/train_log.png", f"{RUN}/animate/preview.html"):
        assert f'"{item}": {{"name"' in results, item  # registered as a report item
    with HeadlessChromium(WIDTH, HEIGHT) as browser:
        browser.goto(report.as_uri())
        open_item(browser, "Tables", "main", "synthetic.html")
        pane = browser.evaluate("(() => { const r = document.querySelector('iframe').getBoundingClientRect(); "
                                "return [r.left, r.right, r.width]; })()")
        assert pane[1] <= WIDTH and pane[2] >= WIDTH / 2, pane  # the main pane, beside the menu
        layout = browser.evaluate_in_frame(TABLE_LAYOUT)
        # The whole table in view: nothing to scroll sideways, the last column inside the pane.
        assert layout["scrollWidth"] <= layout["clientWidth"], layout
        assert layout["lastRight"] <= layout["viewport"] and layout["lastWidth"] > 0, layout
        assert layout["rows"] == 2 + 2 and layout["lastText"] == "0", layout  # 2 header rows; pig and blank

        # In a narrower window the table scrolls inside its box, its first column (sticky) staying put.
        browser.call("Emulation.setDeviceMetricsOverride", width=800, height=HEIGHT, deviceScaleFactor=1, mobile=False)
        moved = browser.evaluate_in_frame("""(() => {
            const box = document.querySelector('div.scroll'), row = box.querySelector('tbody tr');
            const before = [row.cells[0].getBoundingClientRect().left, row.cells[2].getBoundingClientRect().left];
            box.scrollLeft = 100;
            const after = [row.cells[0].getBoundingClientRect().left, row.cells[2].getBoundingClientRect().left];
            return {before, after, scrolled: box.scrollLeft, overflow: box.scrollWidth - box.clientWidth};
        })()""")
        assert moved["overflow"] > 0 and moved["scrolled"] == 100, moved
        assert moved["after"][0] == pytest.approx(moved["before"][0], abs=0.5), moved
        assert moved["after"][1] == pytest.approx(moved["before"][1] - 100, abs=0.5), moved
        browser.call("Emulation.setDeviceMetricsOverride", width=WIDTH, height=HEIGHT, deviceScaleFactor=1, mobile=False)

        open_item(browser, "Animations", "preview", "preview.html")
        video = browser.evaluate_in_frame("(() => { const v = document.querySelector('video'); return v === null ? "
                                          "null : {src: v.src.slice(0, 22), loop: v.loop}; })()")
        assert video == {"src": "data:video/webm;base64", "loop": True}
        # The browser decodes it: the turntable's frame size (PREVIEW_OPTIONS), or -1 after 10 s without.
        size = browser.evaluate_in_frame("""new Promise(done => {
            const v = document.querySelector('video'), size = () => done([v.videoWidth, v.videoHeight]);
            if (v.readyState >= 1) size(); else v.addEventListener('loadedmetadata', size);
            setTimeout(() => done(-1), 10000);
        })""")
        assert size == [160, 160]

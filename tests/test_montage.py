"""The report's montage of a rendered split (pig.render.montage, pig.stages.montage): which views and level it shows,
its error maps against the evaluated ground truth, the PNG it writes, and bad renders named in one line."""
from __future__ import annotations

import numpy as np
import pytest

from pig.data.capture import Capture
from pig.data.raw import CaptureError
from pig.render.montage import error_map, finest_level, montage_views, spread
from pig.stages import montage
from pig._cli import run_cli
from pig._io import write_png
from pig.data.images import read_png

SPLIT = "novel_view"


def truth(capture: Capture, camera: str, frame: int) -> np.ndarray:
    return capture.image(camera, frame) * capture.mask(camera, frame)[..., None]


@pytest.fixture
def rendered(small_capture, tmp_path):
    """renders/novel_view/ with lod0 all white and lod1 (the finest) exact for the first view, half as bright for
    the others; returns (capture, split folder)."""
    capture = Capture.load(small_capture, cache_mb=0)
    split_dir = tmp_path / "renders" / SPLIT
    for index, (camera, frame) in enumerate(capture.views(SPLIT)):
        image = truth(capture, camera, frame)
        write_png(split_dir / "lod0" / camera / f"{frame:08d}.png", np.ones_like(image))
        write_png(split_dir / "lod1" / camera / f"{frame:08d}.png", image if index == 0 else image * 0.5)
    return capture, split_dir


def test_spread_keeps_both_ends_and_every_item_of_short_lists():
    assert spread(list(range(10)), 4) == [0, 3, 6, 9]
    assert spread(list(range(3)), 4) == [0, 1, 2]
    assert spread(["a"], 1) == ["a"]
    with pytest.raises(ValueError, match="at least one view"):
        spread([1, 2], 0)


def test_error_map_is_the_mean_absolute_rgb_difference():
    render = np.zeros((2, 3, 3), np.float32)
    target = np.zeros((2, 3, 3), np.float32)
    target[0, 0] = (0.3, 0.6, 0.9)
    render[1, 2] = (1.0, 0.0, 0.0)
    expected = np.zeros((2, 3))
    expected[0, 0], expected[1, 2] = 0.6, 1 / 3
    np.testing.assert_allclose(error_map(render, target), expected, rtol=1e-6)


def test_montage_shows_the_finest_level_against_the_masked_ground_truth(rendered):
    capture, split_dir = rendered
    assert finest_level(split_dir) == (1, 2)
    views = capture.views(SPLIT)
    shown = montage_views(capture, split_dir, SPLIT, count=3)
    assert [(v.camera, v.frame) for v in shown] == spread(views, 3)
    assert (shown[0].camera, shown[0].frame) == views[0]
    np.testing.assert_array_equal(shown[0].error, 0.0)  # the exact render of lod1, not lod0's white
    for view in shown:
        expected = truth(capture, view.camera, view.frame)
        np.testing.assert_array_equal(view.truth, expected)
        assert view.truth[~capture.mask(view.camera, view.frame)].max() == 0.0
    for view in shown[1:]:
        # Half as bright, within the PNG's 8-bit rounding.
        np.testing.assert_allclose(view.error, error_map(view.truth * 0.5, view.truth), atol=0.5 / 255 + 1e-6)
        assert view.error.max() > 0.05


def test_stage_writes_one_png_of_three_rows(rendered, small_capture, tmp_path):
    _, split_dir = rendered
    output = tmp_path / "montage" / f"{SPLIT}.png"
    assert montage.main(["--capture", str(small_capture), "--renders", str(split_dir), "--split", SPLIT,
                         "--output", str(output), "--views", "2"]) == 0
    image = read_png(output)
    # Two 2-inch columns plus the colour bar, three rows of 48 x 48 px panels, at 100 dpi.
    assert 400 <= image.shape[1] <= 560 and 600 <= image.shape[0] <= 760, image.shape
    assert sorted(p.name for p in output.parent.iterdir()) == [".pig-stage", f"{SPLIT}.png"]


def test_missing_or_mis_sized_render_is_named(rendered, small_capture, tmp_path, capsys):
    capture, split_dir = rendered
    camera, frame = capture.views(SPLIT)[-1]
    last = split_dir / "lod1" / camera / f"{frame:08d}.png"
    write_png(last, np.zeros((10, 12, 3), np.float32))
    with pytest.raises(ValueError, match=rf"{last}: render is 12x10 \(WxH\), the capture's image 48x48"):
        montage_views(capture, split_dir, SPLIT, count=8)
    last.unlink()
    with pytest.raises(CaptureError, match=rf"{last}: image file not found"):
        montage_views(capture, split_dir, SPLIT, count=8)
    output = tmp_path / "montage" / f"{SPLIT}.png"
    empty = tmp_path / "empty" / SPLIT
    empty.mkdir(parents=True)
    assert run_cli(montage.main, ["--capture", str(small_capture), "--renders", str(empty), "--split", SPLIT,
                                  "--output", str(output)]) == 1
    assert capsys.readouterr().err.strip() == (f"montage: error: {empty}: no lod*/ folders; expected the render "
                                                "stage's output for one split")
    assert not output.exists()

"""Probes (pig.avatar.probe): the cheap held-out PSNR of a fit's error-against-time curve, its schedule (the default
run's point count, a resumed fit's), its PSNR against numpy over the same pixels, and train_log.png's series."""
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch
from PIL import Image

from pig.avatar.fit_config import FitConfig
from pig.avatar.probe import box_intrinsics, mask_box, probe_pairs
from pig.avatar.training import evaluations_due
from pig.config import load_preset, load_section
from preset_files import write_test_preset


def test_default_run_has_at_least_ten_held_out_points():
    cfg = load_section(load_preset("cpu-demo"), "fit", FitConfig)
    due = [evaluations_due(cfg, i) for i in range(cfg.iterations + 1)]
    probes = [i for i, (_, probe) in enumerate(due) if probe]
    full = [i for i, (whole, _) in enumerate(due) if whole]
    assert len(probes) >= 10
    assert probes == sorted(set(range(0, cfg.iterations + 1, cfg.probe_every)) | {cfg.iterations})
    assert full == sorted(set(range(cfg.eval_every, cfg.iterations + 1, cfg.eval_every)) | {cfg.iterations})


def test_paper_preset_does_not_probe():
    cfg = load_section(load_preset("paper"), "fit", FitConfig)
    assert cfg.probe_every == 0
    assert [i for i in range(0, cfg.iterations + 1, 1000) if any(evaluations_due(cfg, i))] == \
        sorted(set(range(0, cfg.iterations + 1, cfg.eval_every)) & set(range(0, cfg.iterations + 1, 1000)))


@pytest.mark.parametrize("scale", [1, 2, 3])
def test_mask_box_against_brute_force(rng, scale):
    for trial in range(40):
        height, width = rng.integers(3, 30, size=2)
        mask = rng.random((height, width)) > (1.0 if trial % 10 == 0 else rng.uniform(0.8, 1.0))  # some empty
        box = mask_box(mask, scale)
        ys, xs = np.nonzero(mask)
        if not len(ys):
            assert box is None
            continue
        # The smallest box of whole scale x scale blocks holding the mask, cut to the frame's whole blocks.
        x0 = max(v for v in range(0, width, scale) if v <= xs.min())
        y0 = max(v for v in range(0, height, scale) if v <= ys.min())
        x1 = min(min(v for v in range(scale, width + scale, scale) if v > xs.max()), width // scale * scale)
        y1 = min(min(v for v in range(scale, height + scale, scale) if v > ys.max()), height // scale * scale)
        assert box == (None if x1 <= x0 or y1 <= y0 else (x0, y0, x1, y1))
        if box is not None:  # every mask pixel inside unless cut at the frame's edge
            inside = mask[box[1]:box[3], box[0]:box[2]].sum()
            assert inside == mask.sum() or box[2] == width // scale * scale < width or box[3] == height // scale * scale < height


def test_probe_pairs_start_at_the_middle_frame():
    has = lambda camera, frame: (camera, frame) != ("c1", 30)
    assert probe_pairs([10, 20, 30, 40], ["c0", "c1"], has, 3) == [(30, "c0"), (40, "c0"), (40, "c1")]
    assert probe_pairs([10, 20, 30], ["c0"], has, 5) == [(20, "c0"), (30, "c0"), (10, "c0")]


def test_box_intrinsics_project_onto_the_downscaled_crop(rng):
    K = torch.tensor([[50.0, 0, 31.3], [0, 52.0, 27.9], [0, 0, 1]])
    box, scale = (6, 10, 30, 40), 2
    points = torch.tensor(rng.uniform(-1, 1, (20, 3)) + [0, 0, 4], dtype=torch.float32)
    full = (points @ K.T)[:, :2] / points[:, 2:]
    crop = (points @ box_intrinsics(K, box, scale).T)[:, :2] / points[:, 2:]
    # Original pixel coordinate u covers [u, u+1); the crop's pixel j covers originals [x0 + s j, x0 + s (j + 1)).
    torch.testing.assert_close(crop, (full - torch.tensor(box[:2], dtype=torch.float32)) / scale)


def _read_png(path_stem: Path, mode: str) -> np.ndarray:
    """A held-out view's lossless file read with PIL (1-bit masks as 0 / 255)."""
    [path] = path_stem.parent.glob(path_stem.name + ".png")
    return np.asarray(Image.open(path).convert(mode), dtype=np.float64)


@pytest.mark.slow
@pytest.mark.parametrize("scale", [1, 2])
def test_probe_psnr_equals_numpy_over_the_same_pixels(tiny_fit, scale):
    from pig.avatar.batches import ViewSource
    from pig.avatar.checkpoint import load_avatar
    from pig.avatar.probe import Probe
    from pig.data.capture import Capture
    from pig.render.api import RasterizerConfig, render_gaussians

    capture_dir, avatar = tiny_fit
    capture = Capture.load(capture_dir, cache_mb=0)
    model = load_avatar(avatar, capture=capture)
    raster = RasterizerConfig()
    with ViewSource(capture, list(model.frame_ids), "cpu", 16, 1) as source:
        probe = Probe(capture, model, source, 3, scale)
        value = probe.psnr(model, raster)
    assert len(probe.pairs) == 3
    values = []
    with torch.no_grad():
        for frame, camera in probe.pairs:
            cam = capture.cameras[camera]
            image = _read_png(capture_dir / "images" / camera / f"{frame:08d}", "RGB") / 255
            mask = _read_png(capture_dir / "masks" / camera / f"{frame:08d}", "L") > 127
            truth = image * mask[..., None]
            ys, xs = np.nonzero(mask)
            x0, y0 = xs.min() // scale * scale, ys.min() // scale * scale
            x1 = min(-(-(xs.max() + 1) // scale) * scale, cam.width // scale * scale)
            y1 = min(-(-(ys.max() + 1) // scale) * scale, cam.height // scale * scale)
            h, w = (y1 - y0) // scale, (x1 - x0) // scale
            truth = truth[y0:y1, x0:x1].reshape(h, scale, w, scale, 3).mean((1, 3))
            # The whole frame rendered at 1/scale resolution, then cut to the box: the same pixels as the probe's.
            K = torch.tensor(cam.K, dtype=torch.float32)
            K[:2] /= scale
            g = model.gaussians(model.timestep_of_frame(frame), model.num_levels - 1)
            out = render_gaussians(*g, torch.tensor(cam.viewmat(), dtype=torch.float32)[None], K[None],
                                   cam.width // scale, cam.height // scale, torch.zeros(3))
            render = out.color[0].clamp(0, 1).double().numpy()[y0 // scale:y1 // scale, x0 // scale:x1 // scale]
            values.append(10 * np.log10(1 / np.mean((render - truth) ** 2)))
    assert value == pytest.approx(np.mean(values), abs=2e-4)


@pytest.mark.slow
def test_fit_logs_probes_on_schedule_and_a_resume_keeps_it(small_capture, tmp_path, capsys, monkeypatch):
    from pig.avatar import training
    from pig.avatar.training import fit

    preset = write_test_preset(tmp_path, iterations=12, eval_every=6, probe_every=5, probe_views=2, probe_scale=2,
                     checkpoint_minutes=0.0)
    cfg = load_section(load_preset(preset), "fit", FitConfig)
    drawn, plot = [], training.plot_train_log
    monkeypatch.setattr(training, "plot_train_log",
                        lambda path, rows, title="": (drawn.append(rows[-1]["iteration"]), plot(path, rows, title)))
    monkeypatch.setattr(training, "REDRAW_S", 1e9)  # probes never due a redraw: the start and full evaluations are
    fit(small_capture, tmp_path / "full", preset)
    assert drawn == [0, 6, 12]
    monkeypatch.undo()
    log = pd.read_csv(tmp_path / "full" / "train_log.csv")
    assert log["iteration"][log["probe_psnr"].notna()].tolist() == [i for i in range(13) if evaluations_due(cfg, i)[1]] \
        == [0, 5, 10, 12]
    assert log["iteration"][log["heldout_psnr"].notna()].tolist() == [6, 12]
    probe_at_5 = log.loc[log["iteration"] == 5, "probe_psnr"].item()
    assert f"probe PSNR {probe_at_5:.2f} dB (iteration 5)" in capsys.readouterr().err  # the progress line's
    assert (log["eval_s"].notna() == (log["probe_psnr"].notna() | log["heldout_psnr"].notna())).all()
    # train_s leaves every in-run evaluation out (those at 5, 6 and 10 before the last row), and the checkpoint writes
    # (one an iteration here) too.
    last = log.iloc[-1]
    assert last["wall_s"] - last["train_s"] >= log["eval_s"][log["iteration"].between(1, 11)].sum() - 5e-3

    class Killed(Exception):
        pass

    def kill_at_7(iteration):
        if iteration == 7:
            raise Killed

    with pytest.raises(Killed):
        fit(small_capture, tmp_path / "resumed", preset, on_iteration=kill_at_7)
    fit(small_capture, tmp_path / "resumed", preset)
    resumed = pd.read_csv(tmp_path / "resumed" / "train_log.csv")
    for column in ("probe_psnr", "heldout_psnr"):  # the same iterations and, bit-identical CPU fits, values
        pd.testing.assert_series_equal(resumed[column], log[column])


def test_train_log_png_draws_binned_losses_and_every_psnr(monkeypatch):
    from pig.avatar import train_plot

    cfg = load_section(load_preset("cpu-demo"), "fit", FitConfig)
    rows = [{"iteration": i, "wall_s": 0.3 * i, "train_s": 0.25 * i, "loss": "" if i == 0 else 1 / i, "l1": "",
             "ssim": "", "lpips": "", "heldout_psnr": 20 + i / 900 if evaluations_due(cfg, i)[0] else "",
             "heldout_psnr_iterate": "", "probe_psnr": 18 + i / 900 if evaluations_due(cfg, i)[1] else ""}
            for i in range(cfg.iterations + 1)]
    drawn = {}
    monkeypatch.setattr(train_plot, "write_figure", lambda path, figure, dpi=None: drawn.update(figure=figure))
    train_plot.plot_train_log(Path("unused.png"), rows, "title")
    ax_loss, ax_psnr = drawn["figure"].axes
    for ax in (ax_loss, ax_psnr):
        assert ax.get_xlabel().endswith("[s]")
    assert ax_psnr.get_ylabel().startswith("held-out novel-view PSNR [dB]")
    [loss] = ax_loss.get_lines()
    # 1800 logged losses as 200 means of 9 consecutive rows each.
    times = np.array([r["train_s"] for r in rows[1:]])
    losses = np.array([r["loss"] for r in rows[1:]])
    np.testing.assert_allclose(loss.get_xdata(), times.reshape(200, 9).mean(1))
    np.testing.assert_allclose(loss.get_ydata(), losses.reshape(200, 9).mean(1))
    probe, full = ax_psnr.get_lines()
    expected = [(r["train_s"], r["probe_psnr"]) for r in rows if r["probe_psnr"] != ""]
    assert list(zip(probe.get_xdata(), probe.get_ydata())) == expected and len(expected) >= 10
    assert list(zip(full.get_xdata(), full.get_ydata())) == [(r["train_s"], r["heldout_psnr"]) for r in rows
                                                               if r["heldout_psnr"] != ""]
    assert full.get_linestyle() == "None" and probe.get_linestyle() == "-"


def test_tables_training_plot_draws_probes_where_the_log_has_them(tmp_path, monkeypatch):
    from pig.stages import tables

    logs = {}
    for variant, probed in (("pig", True), ("no_precond", False)):
        path = tmp_path / "synthetic" / "s0" / variant / "train_log.csv"
        path.parent.mkdir(parents=True)
        frame = pd.DataFrame({"iteration": [0, 5, 10, 12], "wall_s": [0.0, 5.0, 10.5, 13.0],
                              "train_s": [0.0, 4.9, 10.0, 12.2], "heldout_psnr": [np.nan, np.nan, 21.0, 22.0]})
        if probed:
            frame["probe_psnr"] = [15.0, 16.0, 17.0, 18.0]
        frame.to_csv(path, index=False)
        logs[variant] = {path: tables.read_train_log(path)}
    drawn = []
    monkeypatch.setattr(tables, "write_figure", lambda path, figure, dpi=None: drawn.extend(
        (line.get_label(), list(line.get_xdata()), list(line.get_ydata())) for line in figure.axes[0].get_lines()))
    tables.training_plot(logs, tmp_path / "plot.png", "t")
    by_label = {label: (x, y) for label, x, y in drawn}
    assert by_label["pig (s0)"] == ([0.0, 4.9, 10.0, 12.2], [15.0, 16.0, 17.0, 18.0])
    assert by_label["no_precond (s0)"] == ([10.0, 12.2], [21.0, 22.0])
    # The probed fit's full evaluations: unlabelled markers beside its line, left out of the legend.
    assert [(x, y) for label, x, y in drawn if label.startswith("_")] == [([10.0, 12.2], [21.0, 22.0])]

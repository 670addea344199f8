"""Render storage (pig.data.render_store): lossless chunks, resume after a kill, the capture they were rendered for."""
import io
import json
import re
import shutil
import zipfile
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from pig._io import write_png
from pig.data.capture import Capture
from pig.data.capture_record import RECORD
from pig.data.exr import read_exr
from pig.data.images import read_png
from pig.data.raw import CaptureError
from pig.data.render_store import CODECS, ChunkEncoder, RenderReader, chunk_path, read_manifest, write_manifest
from pig.render.api import RasterizerConfig
from pig.stages import render as render_stage
from pig.stages.evaluate import EvaluateConfig, evaluate_split
from pig.stages.render import render_split

SPLIT = "novel_view"  # 2 cameras x 3 frames in the small capture: chunks of 2 frames and 1


def _textured(rng, frames: int, height: int = 37, width: int = 53) -> np.ndarray:
    """Renders-like uint8 views: black background, a smooth body with noise on it."""
    yy, xx = np.mgrid[:height, :width]
    body = ((yy - height / 2) ** 2 / (height / 3) ** 2 + (xx - width / 2) ** 2 / (width / 4) ** 2) < 1
    images = rng.integers(0, 256, (frames, height, width, 3)) * body[None, ..., None]
    images[0, 0, 0] = 255  # the extremes survive
    return images.astype(np.uint8)


def _manifest(split_dir, frames: list[int], chunk_frames: int, codec: str = "png", cameras=("cam00",)) -> None:
    """The render stage's manifest of a split folder whose chunks a test writes itself."""
    write_manifest(split_dir, {"split": SPLIT, "cameras": list(cameras), "frames": frames, "levels": [0],
                               "chunk_frames": chunk_frames, "codec": codec, "every_view": False})


@pytest.mark.parametrize("codec", sorted(CODECS))
def test_chunks_round_trip_exactly_and_read_like_per_view_pngs(codec, tmp_path, rng):
    images = _textured(rng, 5)
    frames = [3, 4, 7, 8, 11]
    encoder = ChunkEncoder(codec, workers=2, pending=1, pending_views=1)  # both waits taken
    for frame, image in zip(frames[:3], images[:3]):
        encoder.add(chunk_path(tmp_path / "lod0", "cam00", 3), frame, image)
    encoder.finish_chunk(chunk_path(tmp_path / "lod0", "cam00", 3), "cam00", 0)
    for frame, image in zip(frames[3:], images[3:]):
        encoder.add(chunk_path(tmp_path / "lod0", "cam00", 8), frame, image)
    encoder.finish_chunk(chunk_path(tmp_path / "lod0", "cam00", 8), "cam00", 0)
    written = encoder.close()
    _manifest(tmp_path, frames, 3, codec)
    assert written == sum(p.stat().st_size for p in (tmp_path / "lod0" / "cam00").iterdir())
    reader = RenderReader(tmp_path / "lod0", {"cam00": (53, 37)})
    for frame, image in zip(frames[::-1], images[::-1]):  # out of order: chunks are reopened
        np.testing.assert_array_equal(reader.image_u8("cam00", frame), image)
        # The float view equals what read_png gives for the same view written as a PNG.
        write_png(tmp_path / "png" / f"{frame:08d}.png", image)
        np.testing.assert_array_equal(reader.image("cam00", frame), read_png(tmp_path / "png" / f"{frame:08d}.png"))
    assert not reader.has("cam00", 5) and not reader.has("cam01", 3)


def test_quantisation_matches_the_png_writer(rng):
    colour = torch.from_numpy(rng.random((9, 11, 3)) * 1.2 - 0.1).float()
    colour[0, :4, 0] = torch.tensor([0.5 / 255, 1.5 / 255, 2.5 / 255, 254.5 / 255])  # ties round half to even
    expected = np.round(np.clip(colour.numpy(), 0, 1) * 255).astype(np.uint8)  # write_png's rule
    np.testing.assert_array_equal(render_stage._to_u8(colour), expected)
    # A camera group's views at once (the stage's call) give each view what it gives alone.
    group = torch.stack([colour, colour.flip(0), 1 - colour])
    converted = render_stage._to_u8(group)
    assert converted.shape == (3, 9, 11, 3) and converted.dtype == np.uint8
    for view in range(3):
        np.testing.assert_array_equal(converted[view], render_stage._to_u8(group[view]))


def test_a_cut_short_or_foreign_chunk_is_refused_by_name(tmp_path, rng):
    encoder = ChunkEncoder("png")
    level = tmp_path / "lod0"
    path = chunk_path(level, "cam00", 0)
    for frame, image in enumerate(_textured(rng, 2)):
        encoder.add(path, frame, image)
    encoder.finish_chunk(path, "cam00", 0)
    encoder.close()
    _manifest(tmp_path, [0, 1], 2)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(CaptureError, match=rf"{path}: not a valid npz archive"):
        RenderReader(level).image("cam00", 0)
    np.savez(path, frames=np.arange(2))
    with pytest.raises(CaptureError, match=rf"{path}: missing \['offsets', 'data', 'codec', 'camera', 'lod'\]"):
        RenderReader(level).image("cam00", 0)
    # A member declaring 8 TB is refused from its header, before anything is allocated or read.
    header = io.BytesIO()
    np.lib.format.write_array_header_1_0(header, {"descr": "|u1", "fortran_order": False, "shape": (8 * 10 ** 12,)})
    np.savez(path, frames=np.arange(2), offsets=np.array([0, 1, 2]), codec=np.array("png"))
    with zipfile.ZipFile(path, "a") as archive:
        archive.writestr("data.npy", header.getvalue() + b"\0" * 16)
    with pytest.raises(CaptureError, match=rf"{path}: member 'data' declares shape \(8000000000000,\) of uint8"):
        RenderReader(level).image("cam00", 0)


@pytest.fixture(scope="module")
def rendered(tiny_fit, tmp_path_factory):
    """(capture, checkpoint, renders of SPLIT with --every-view) of the tiny fit."""
    capture, checkpoint = tiny_fit
    renders = tmp_path_factory.mktemp("store") / "renders" / SPLIT
    cfg = EvaluateConfig(timing_frames=1, chunk_frames=2)
    render_split(checkpoint, capture, SPLIT, renders, cfg, RasterizerConfig(backend="cpu"), every_view=True)
    return capture, checkpoint, renders


@pytest.mark.slow
def test_every_view_pngs_and_exrs_match_the_chunks(rendered):
    capture, _, renders = rendered
    manifest = read_manifest(renders)
    assert manifest["every_view"] and manifest["levels"] == [0, 1]
    assert json.loads((renders / RECORD).read_text())["fingerprint"] == Capture.load(capture).fingerprint()
    for level in manifest["levels"]:
        reader = RenderReader(renders / f"lod{level}")
        for cam in manifest["cameras"]:
            assert len(list((renders / f"lod{level}" / cam).glob("*.npz"))) == -(-len(manifest["frames"]) // 2)
            for frame in manifest["frames"]:
                png = renders / f"lod{level}" / cam / f"{frame:08d}.png"
                np.testing.assert_array_equal(reader.image(cam, frame), read_png(png))
                exr = read_exr(png.with_suffix(".exr"))
                assert set(exr) == {"A", "Z"} and exr["A"].shape == reader.image(cam, frame).shape[:2]


@pytest.mark.slow
def test_a_killed_render_resumes_with_only_the_missing_chunks(rendered, tmp_path, monkeypatch):
    capture, checkpoint, reference = rendered
    cfg = EvaluateConfig(timing_frames=1, chunk_frames=2, every_view=True)
    renders = tmp_path / "renders" / SPLIT
    frames = read_manifest(reference)["frames"]
    calls = []
    original = render_stage.SplitRenderer.gaussians

    def counted(self, frame, lod):
        calls.append((frame, lod))
        if len(calls) == 2 * 2 + 1 and not getattr(counted, "killed", False):  # the second chunk's first frame
            counted.killed = True
            raise KeyboardInterrupt
        return original(self, frame, lod)

    monkeypatch.setattr(render_stage.SplitRenderer, "gaussians", counted)
    with pytest.raises(KeyboardInterrupt):
        render_split(checkpoint, capture, SPLIT, renders, cfg, RasterizerConfig(backend="cpu"))
    assert not renders.exists()  # nothing half-made under the final name: evaluate cannot score it
    partial = renders.with_name(f".{SPLIT}.partial")
    assert sorted(p.name for p in (partial / "lod0" / read_manifest(reference)["cameras"][0]).glob("*.npz")) == [
        f"{frames[0]:08d}.npz"]
    calls.clear()
    render_split(checkpoint, capture, SPLIT, renders, cfg, RasterizerConfig(backend="cpu"))
    rendered_again = [call for call in calls if call[0] in frames[:2]]
    timed = 2 * 2  # seconds_per_frame: one warm-up and one timed frame per LOD
    assert len(calls) - timed == 2 * (len(frames) - 2) and len(rendered_again) <= timed
    assert not partial.exists()
    # The resumed render equals the uninterrupted one, view for view, and its splat track too.
    for level in (0, 1):
        for cam in read_manifest(reference)["cameras"]:
            got, want = RenderReader(renders / f"lod{level}"), RenderReader(reference / f"lod{level}")
            for frame in frames:
                np.testing.assert_array_equal(got.image_u8(cam, frame), want.image_u8(cam, frame))
        for key in ("frames", "centres", "opacities"):
            with np.load(renders / f"lod{level}" / "splats.npz") as a, np.load(reference / f"lod{level}" / "splats.npz") as b:
                np.testing.assert_array_equal(a[key], b[key])
        assert not list((renders / f"lod{level}").glob(".splats-*"))


@pytest.mark.slow
def test_evaluate_refuses_renders_of_another_capture(rendered, tmp_path):
    capture, _, renders = rendered
    other = tmp_path / "capture"
    shutil.copytree(capture, other)
    cameras = json.loads((other / "cameras.json").read_text())
    first = sorted(cameras)[0]
    cameras[first]["K"][0][0] *= 1.01
    (other / "cameras.json").write_text(json.dumps(cameras))
    expected = f"{renders}: made from another capture ({capture.resolve()}) than {other}: their cameras differ"
    with pytest.raises(CaptureError, match=re.escape(expected)):
        evaluate_split(other, renders, SPLIT, tmp_path / "metrics", EvaluateConfig())
    assert not (tmp_path / "metrics" / f"{SPLIT}_lod0.json").exists()


def test_chunked_batched_evaluation_equals_per_image_scores_of_per_view_pngs(tmp_path, rng):
    """50 views scored from chunks in batches of 16 (decoded on threads) against each view scored alone from its
    PNG: PSNR within 1e-4 dB, SSIM within 1e-5, LPIPS (random stand-in weights) within 1e-5."""
    from test_metrics import _tiny_capture

    from pig.metrics.lpips import LPIPS
    from pig.metrics.psnr import psnr
    from pig.metrics.ssim import ssim
    from pig.stages.evaluate import evaluate_levels

    capture_dir, renders = _tiny_capture(tmp_path, rng, frames=50)
    encoder = ChunkEncoder("webp")
    for frame in range(50):
        path = chunk_path(tmp_path / "chunked" / "lod0", "cam00", frame // 16 * 16)
        encoder.add(path, frame, np.round(read_png(renders / "lod0" / "cam00" / f"{frame:08d}.png") * 255).astype(np.uint8))
        if frame % 16 == 15 or frame == 49:
            encoder.finish_chunk(path, "cam00", 0)
    encoder.close()
    _manifest(tmp_path / "chunked", list(range(50)), 16, "webp")
    capture = Capture.load(capture_dir, cache_mb=0)
    lpips = LPIPS("alex", weights="random")
    table, _ = evaluate_levels(capture, "novel_view", {0: tmp_path / "chunked" / "lod0"},
                               EvaluateConfig(batch_size=16, encode_workers=2), lpips, None, torch.device("cpu"))[0]
    assert len(table) == 50
    for row in table.itertuples():
        render = torch.from_numpy(read_png(renders / "lod0" / "cam00" / f"{row.frame:08d}.png")).permute(2, 0, 1)[None]
        truth = capture.image("cam00", row.frame) * capture.mask("cam00", row.frame)[..., None]
        truth = torch.from_numpy(truth).permute(2, 0, 1)[None]
        assert row.psnr == pytest.approx(float(psnr(render, truth)), abs=1e-4)
        assert row.ssim == pytest.approx(float(ssim(render, truth)), abs=1e-5)
        assert row.lpips == pytest.approx(float(lpips(render, truth)), abs=1e-5)


def test_every_lod_in_one_pass_equals_each_view_scored_alone(tmp_path, rng, monkeypatch):
    """Two LODs of 24 views scored in one pass (batches of 16, decoded on 3 threads) against each view scored alone
    from its PNG: PSNR within 1e-4 dB, SSIM within 1e-5, LPIPS (random stand-in weights) within 1e-5; each LOD's
    FID (a stand-in Inception) within 1e-6 of np.cov statistics of all its views' features at once; and every
    ground-truth view decoded once for both LODs."""
    from test_metrics import _TinyInception, _tiny_capture

    from pig.metrics.fid import InceptionFeatures, frechet_distance
    from pig.metrics.lpips import LPIPS
    from pig.metrics.psnr import psnr
    from pig.metrics.ssim import ssim
    from pig.stages.evaluate import evaluate_levels

    frames = 24
    capture_dir, renders = _tiny_capture(tmp_path, rng, frames=frames)
    pngs = {0: renders / "lod0" / "cam00", 1: tmp_path / "lod1_png"}
    pngs[1].mkdir()
    for frame in range(frames):  # the coarser LOD: the finer one's renders with noise, another set of scores
        image = read_png(pngs[0] / f"{frame:08d}.png")
        write_png(pngs[1] / f"{frame:08d}.png", np.clip(image + rng.normal(0, 0.1, image.shape), 0, 1))
    encoder = ChunkEncoder("png")
    for level, folder in pngs.items():
        for frame in range(frames):
            path = chunk_path(tmp_path / "chunked" / f"lod{level}", "cam00", frame // 16 * 16)
            encoder.add(path, frame, np.round(read_png(folder / f"{frame:08d}.png") * 255).astype(np.uint8))
            if frame % 16 == 15 or frame == frames - 1:
                encoder.finish_chunk(path, "cam00", level)
    encoder.close()
    _manifest(tmp_path / "chunked", list(range(frames)), 16, "png")
    torch.manual_seed(0)
    torch.jit.script(_TinyInception()).save(str(tmp_path / "inception.pt"))
    inception = InceptionFeatures(tmp_path / "inception.pt")
    lpips = LPIPS("alex", weights="random")
    capture = Capture.load(capture_dir, cache_mb=0)
    reads = []
    original = Capture.image_u8
    monkeypatch.setattr(Capture, "image_u8", lambda self, cam, frame: reads.append((cam, frame)) or original(self, cam, frame))

    results = evaluate_levels(capture, "novel_view", {level: tmp_path / "chunked" / f"lod{level}" for level in pngs},
                              EvaluateConfig(batch_size=16, encode_workers=3), lpips, inception, torch.device("cpu"))
    assert sorted(reads) == [("cam00", frame) for frame in range(frames)]
    as_batch = lambda images: torch.from_numpy(np.stack(images)).permute(0, 3, 1, 2)  # noqa: E731
    truths = as_batch([capture.image("cam00", f) * capture.mask("cam00", f)[..., None] for f in range(frames)])
    real = inception(truths).double().numpy()
    for level, folder in pngs.items():
        table, summary = results[level]
        assert table["frame"].tolist() == list(range(frames))
        for row in table.itertuples():
            render = as_batch([read_png(folder / f"{row.frame:08d}.png")])
            truth = truths[row.frame:row.frame + 1]
            assert row.psnr == pytest.approx(float(psnr(render, truth)), abs=1e-4)
            assert row.ssim == pytest.approx(float(ssim(render, truth)), abs=1e-5)
            assert row.lpips == pytest.approx(float(lpips(render, truth)), abs=1e-5)
        fake = inception(as_batch([read_png(folder / f"{f:08d}.png") for f in range(frames)])).double().numpy()
        expected = frechet_distance(fake.mean(0), np.cov(fake, rowvar=False), real.mean(0), np.cov(real, rowvar=False))
        assert expected > 0 and summary["fid"] == pytest.approx(expected, rel=1e-6)
    assert (results[0][0]["psnr"] != results[1][0]["psnr"]).all()  # each LOD scored its own renders


def test_lpips_against_reference_taps_equals_the_pair_forward(rng):
    """LPIPS.distance of several image sets against one set's `reference` taps equals forward on each pair."""
    from pig.metrics.lpips import LPIPS

    net = LPIPS("alex", weights="random")
    y = torch.from_numpy(rng.random((3, 3, 40, 36), dtype=np.float32))
    reference = net.reference(y)
    for _ in range(2):
        x = torch.from_numpy(rng.random((3, 3, 40, 36), dtype=np.float32))
        torch.testing.assert_close(net.distance(x, reference), net(x, y), rtol=0, atol=0)
    with pytest.raises(ValueError, match="2 images against a reference of 3"):
        net.distance(y[:2], reference)
# Sweep three, case 6: crafted chunks. A chunk of cam00 at LOD 0 holding frames 0 and 1 (the manifest's run), with
# one member replaced; each is refused naming the chunk and what was expected, before a wrong view is returned.
WIDTH, HEIGHT = 53, 37


def _streams(rng, codec: str = "png") -> list[np.ndarray]:
    from pig.data.render_store import encode_image

    return [encode_image(image, codec) for image in _textured(rng, 2, HEIGHT, WIDTH)]


def _crafted(split_dir, rng, **replaced) -> Path:
    """lod0/cam00/00000000.npz of frames 0 and 1 (or as many as `streams`) as write_chunk writes it, with `replaced`
    members; its split folder's manifest."""
    streams = replaced.pop("streams", None) or _streams(rng)
    frames = list(range(len(streams)))
    offsets = np.cumsum([0, *map(len, streams)]).astype(replaced.pop("offsets_dtype", np.int64))
    members = {"frames": np.array(frames), "offsets": offsets,
               "data": np.concatenate(streams), "codec": np.array("png"), "camera": np.array("cam00"),
               "lod": np.array(0)}
    path = chunk_path(split_dir / "lod0", "cam00", 0)
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez(path, **{**members, **replaced})
    _manifest(split_dir, frames, len(frames), cameras=("cam00", "cam01"))
    return path


def _gray_png(rng) -> np.ndarray:
    return cv2.imencode(".png", _textured(rng, 1, HEIGHT, WIDTH)[0, ..., 0])[1].reshape(-1)


def _wider_png() -> np.ndarray:
    return cv2.imencode(".png", np.zeros((HEIGHT, WIDTH + 1, 3), np.uint8))[1].reshape(-1)


def _jpeg(rng) -> np.ndarray:
    return cv2.imencode(".jpg", _textured(rng, 1, HEIGHT, WIDTH)[0], [cv2.IMWRITE_JPEG_QUALITY, 100])[1].reshape(-1)


CRAFTED = {
    "float frame ids": (lambda rng: {"frames": np.array([0.0, 1.0])}, "member 'frames' declares shape (2,) of float64"),
    "numeric string frame ids": (lambda rng: {"frames": np.array(["0", "1"])}, "member 'frames' declares shape (2,)"),
    "frame ids int() cannot read": (lambda rng: {"frames": np.array(["a", "b"])}, "member 'frames' declares"),
    "frame ids reversed": (lambda rng: {"frames": np.array([1, 0])}, "holds frames [1, 0], expected [0, 1]"),
    "float offsets": (lambda rng: {"offsets_dtype": float}, "member 'offsets' declares shape (3,) of float64"),
    "a grayscale PNG": (lambda rng: {"streams": [_gray_png(rng), _gray_png(rng)]}, "is not an 8-bit RGB PNG"),
    "a JPEG": (lambda rng: {"streams": [_jpeg(rng), _jpeg(rng)]}, "is not an 8-bit RGB PNG"),
    "another camera's chunk": (lambda rng: {"camera": np.array("cam01")}, "a chunk of camera 'cam01' at LOD 0"),
    "another LOD's chunk": (lambda rng: {"lod": np.array(1)}, "a chunk of camera 'cam00' at LOD 1"),
    "a view of another size": (lambda rng: {"streams": [_wider_png(), _wider_png()]},
                               f"the image is {WIDTH + 1}x{HEIGHT} (WxH), camera cam00 is {WIDTH}x{HEIGHT}"),
}


@pytest.mark.parametrize("case", sorted(CRAFTED))
def test_a_crafted_chunk_is_refused_naming_it_and_what_was_expected(tmp_path, rng, case):
    """Accepted silently before: frame ids as floats or strings (int() of each), reversed, another camera's or
    LOD's chunk copied over, grayscale or JPEG streams in a lossless chunk; others failed with `invalid literal for
    int()` or `slice indices must be integers`, naming no file."""
    replaced, expected = CRAFTED[case]
    path = _crafted(tmp_path, rng, **replaced(rng))
    reader = RenderReader(tmp_path / "lod0", {"cam00": (WIDTH, HEIGHT), "cam01": (WIDTH, HEIGHT)})
    with pytest.raises(CaptureError) as refused:
        reader.image("cam00", 0)
    assert str(refused.value).startswith(str(path)) and expected in str(refused.value)
    assert "re-render the split" in str(refused.value) or "not read" in str(refused.value)


def test_the_crafted_chunk_template_reads_back(tmp_path, rng):
    """The chunk the cases above alter is itself a valid chunk: each refusal is the altered member's."""
    images = _textured(np.random.default_rng(0), 2, HEIGHT, WIDTH)
    _crafted(tmp_path, np.random.default_rng(0))
    reader = RenderReader(tmp_path / "lod0", {"cam00": (WIDTH, HEIGHT)})
    for frame in (0, 1):
        np.testing.assert_array_equal(reader.image_u8("cam00", frame), images[frame])


def test_a_chunk_declaring_twenty_million_frame_ids_is_refused_before_they_are_read(tmp_path, monkeypatch):
    """A 160 MB frames member (under the 1 GiB bound per member) was read and indexed into a dict (~10 GB in
    evaluate) before anything looked at the split. Now its header is checked against the manifest's run of 2
    frames first: nothing past the headers is read (a counting reader stops at 1 MiB)."""
    count, block = 20_000_000, bytes(1_000_000)
    path = chunk_path(tmp_path / "lod0", "cam00", 0)
    path.parent.mkdir(parents=True)
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as archive:
        with archive.open("frames.npy", "w", force_zip64=True) as member:
            np.lib.format.write_array_header_1_0(member, {"descr": "<i8", "fortran_order": False, "shape": (count,)})
            for _ in range(count * 8 // len(block)):
                member.write(block)
    _manifest(tmp_path, [0, 1], 2)
    read = []
    original = zipfile.ZipExtFile.read

    def counted(self, n=-1):
        data = original(self, n)
        read.append(len(data))
        if sum(read) > 1 << 20:
            raise MemoryError(f"{sum(read):,} bytes read from the chunk's members")
        return data

    monkeypatch.setattr(zipfile.ZipExtFile, "read", counted)
    with pytest.raises(CaptureError, match=re.escape(f"{path}: member 'frames' declares shape ({count},) of int64, "
                                                     "expected (2,) integers")):
        RenderReader(tmp_path / "lod0").image("cam00", 0)
    assert sum(read) < 1024


def test_evaluate_refuses_a_view_of_another_size_naming_its_chunk(tmp_path, rng):
    """A chunk whose views are another size than the capture's camera stopped evaluate at np.stack ("all input
    arrays must have the same shape"), naming no file."""
    from test_metrics import _tiny_capture

    from pig.data.render_store import encode_image
    from pig.stages.evaluate import evaluate_levels

    capture_dir, _ = _tiny_capture(tmp_path, rng, frames=3)  # 40 x 32
    split = tmp_path / "chunked"
    _crafted(split, rng, streams=[encode_image(_textured(rng, 1, 32, 40 if f else 41)[0], "png") for f in range(3)])
    capture = Capture.load(capture_dir, cache_mb=0)
    with pytest.raises(CaptureError, match=re.escape(f"{chunk_path(split / 'lod0', 'cam00', 0)} (frame 0): the image "
                                                     "is 41x32 (WxH), camera cam00 is 40x32")):
        evaluate_levels(capture, "novel_view", {0: split / "lod0"}, EvaluateConfig(batch_size=3, encode_workers=1),
                        None, None, torch.device("cpu"))


def test_chunks_of_format_one_without_camera_and_lod_are_still_read(tmp_path, rng):
    """Renders written before chunks named their camera and LOD read as before; every other check applies."""
    images = _textured(np.random.default_rng(0), 2, HEIGHT, WIDTH)
    path = _crafted(tmp_path, np.random.default_rng(0))
    with np.load(path) as chunk:
        np.savez(path, **{key: chunk[key] for key in ("frames", "offsets", "data", "codec")})
    manifest = json.loads((tmp_path / "manifest.json").read_text())
    (tmp_path / "manifest.json").write_text(json.dumps({**manifest, "format": "pig-render-chunks/1"}))
    reader = RenderReader(tmp_path / "lod0", {"cam00": (WIDTH, HEIGHT)})
    for frame in (0, 1):
        np.testing.assert_array_equal(reader.image_u8("cam00", frame), images[frame])
    manifest["format"] = "pig-render-chunks/2"  # the same chunk under a manifest of format 2: its ids are required
    (tmp_path / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(CaptureError, match=re.escape(f"{path}: missing ['camera', 'lod']")):
        RenderReader(tmp_path / "lod0").image_u8("cam00", 0)


def test_a_view_the_manifest_does_not_list_is_reported_against_the_manifest(tmp_path, rng):
    """It was reported as a missing per-view PNG that nothing had ever written."""
    _crafted(tmp_path, rng)
    reader = RenderReader(tmp_path / "lod0")
    for camera, frame in (("cam00", 5), ("cam02", 0)):
        assert not reader.has(camera, frame)
        with pytest.raises(CaptureError, match=re.escape(f"{tmp_path / 'manifest.json'}: lists no view of camera "
                                                         f"{camera!r} at frame {frame}")):
            reader.image(camera, frame)
    chunk_path(tmp_path / "lod0", "cam01", 0).parent.mkdir()  # listed, but its chunk is not there
    with pytest.raises(CaptureError, match=re.escape(f"{chunk_path(tmp_path / 'lod0', 'cam01', 0)}: missing")):
        reader.image("cam01", 1)

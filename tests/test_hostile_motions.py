"""Hostile and unlucky motions for `pig animate` and `pig export`: frame rates, lengths, translations and shapes no
capture could hold are refused naming the file, before anything large is allocated; a few frames of a long motion
are read alone."""
from __future__ import annotations

import resource
import tracemalloc
import zipfile
from contextlib import contextmanager

import numpy as np
import pytest
from test_export import checkpoint  # noqa: F401  (the fixture: a small untrained avatar)

import pig.body.npz as npz
from pig._cli import run_cli
from pig.body.motion import DEMO_MOTION, Motion, MotionError, read_motion
from pig.stages.animate import main as animate_main
from pig.stages.export import main as export_main

STAGES = {"animate": animate_main, "export": export_main}
GIB = 1 << 30


@contextmanager
def address_space_limit(extra_bytes: int):
    """For the block the process may map at most `extra_bytes` more than it has mapped now (RLIMIT_AS, soft limit
    only, restored after): an allocation past that fails at once instead of taking the machine's memory."""
    soft, hard = resource.getrlimit(resource.RLIMIT_AS)
    with open("/proc/self/status") as status:
        mapped = next(int(line.split()[1]) * 1024 for line in status if line.startswith("VmSize:"))
    limit = mapped + extra_bytes if hard == resource.RLIM_INFINITY else min(hard, mapped + extra_bytes)
    resource.setrlimit(resource.RLIMIT_AS, (limit, hard))
    try:
        yield
    finally:
        resource.setrlimit(resource.RLIMIT_AS, (soft, hard))


def _demo(path, **changes) -> str:
    """The shipped demo clip (144 frames, AMASS layout) with some arrays replaced, written to `path`."""
    with np.load(DEMO_MOTION) as shipped:
        arrays = {key: shipped[key] for key in shipped.files}
    arrays.update(changes)
    np.savez(path, **arrays)
    return str(path)


def _run(stage: str, checkpoint, output, motion: str, *extra: str) -> list[str]:
    argv = ["--checkpoint", str(checkpoint), "--output", str(output), "--motion", motion, *extra]
    return argv + (["--size", "16", "16", "--device", "cpu"] if stage == "animate" else [])


def _refused(capsys, stage: str, argv: list[str]) -> str:
    """The stage's one error line for `argv` (exit status 1)."""
    code = run_cli(STAGES[stage], argv)
    err = capsys.readouterr().err
    assert code == 1 and err.startswith(f"{stage}: error: ") and err.count("\n") == 1, err
    return err


@pytest.mark.parametrize("stage", ["animate", "export"])
@pytest.mark.parametrize("rate", [0.001, 1e-6, 5000.0])
def test_a_motion_declaring_an_absurd_frame_rate_is_refused_before_allocating(checkpoint, tmp_path, capsys,  # noqa: F811
                                                                              stage, rate):
    # 0.001 fps resampled to 30 fps was 4.3 million frames (7 GiB of poses); 1e-6 fps asked for 32 GiB at once.
    motion = _demo(tmp_path / "slow.npz", mocap_framerate=np.array(rate))
    extra = ["--fps", "30"] if stage == "animate" else []
    with address_space_limit(GIB):
        err = _refused(capsys, stage, _run(stage, checkpoint, tmp_path / "out", motion, *extra))
    assert f"{motion}: `mocap_framerate` is {rate:g} fps" in err  # the file and its rate, not the video encoder
    assert not (tmp_path / "out").exists()


def test_resampling_to_more_than_max_frames_is_refused_before_allocating():
    from pig.body.motion import MAX_FRAMES

    clip = Motion(np.zeros((144, 55, 3)), np.zeros((144, 3)), fps=1.0, source="clip")  # 143 s
    assert 143 * 1000 + 1 > MAX_FRAMES
    tracemalloc.start()
    try:
        with pytest.raises(MotionError, match="143 s at 1000 fps is 143,001 frames"):
            clip.resample(1000.0)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 1 << 20  # no array of the 143,001 frames was made
    assert clip.resample(2.0).num_frames == 287  # within the bound it resamples


def test_a_still_pose_longer_than_max_frames_is_refused(checkpoint, tmp_path, capsys):  # noqa: F811
    argv = ["--checkpoint", str(checkpoint), "--output", str(tmp_path / "out"), "--seconds", "3600", "--fps", "1000",
            "--size", "16", "16", "--device", "cpu"]
    with address_space_limit(GIB):  # 3.6 million poses were 4.75 GB
        err = _refused(capsys, "animate", argv)
    assert "3,600,000 frames" in err and not (tmp_path / "out").exists()


FAR = {"every frame": (slice(None), 0), "a jump after frame 10": (slice(10, None), 10)}


@pytest.mark.parametrize("stage", ["animate", "export"])
@pytest.mark.parametrize("case", ["every frame", "a jump after frame 10", "NaN at frame 12"])
def test_translations_no_capture_could_hold_are_refused_naming_file_frame_and_value(checkpoint, tmp_path,  # noqa: F811
                                                                                    capsys, stage, case):
    with np.load(DEMO_MOTION) as shipped:
        trans = shipped["trans"].astype(np.float64)
    if case == "NaN at frame 12":
        trans[12, 1], frame = np.nan, 12
    else:
        rows, frame = FAR[case]
        trans[rows, 0] = 1e30  # before: a black video (animate) or splats collapsed onto ~30 points (export), exit 0
    motion = _demo(tmp_path / "far.npz", trans=trans)
    err = _refused(capsys, stage, _run(stage, checkpoint, tmp_path / "out", motion, "--frames", "0:20"))
    assert f"{motion}: the translation of frame {frame} is {trans[frame].tolist()}" in err
    assert not (tmp_path / "out").exists()
    # Only the frames asked for are read and checked: the first ten are fine.
    if case == "a jump after frame 10" and stage == "export":
        assert run_cli(export_main, _run(stage, checkpoint, tmp_path / "out", motion, "--frames", "0:10")) == 0


def test_far_translations_given_as_arrays_are_refused(checkpoint, tmp_path):  # noqa: F811
    from pig.avatar.export import export_avatar

    transl = np.zeros((3, 3))
    transl[2] = [0.0, -2e3, 0.0]
    with pytest.raises(MotionError, match=r"poses: the translation of frame 2 is \[0.0, -2000.0, 0.0\]"):
        export_avatar(checkpoint, tmp_path / "out", poses=np.zeros((3, 55, 3)), transl=transl, motion_source="poses")
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("stage", ["animate", "export"])
def test_shape_coefficients_beyond_ten_standard_deviations_are_refused(checkpoint, tmp_path, capsys,  # noqa: F811
                                                                       stage):
    betas = np.zeros(10, dtype=np.float32)
    betas[3] = 1e30
    motion = _demo(tmp_path / "shape.npz", betas=betas)
    err = _refused(capsys, stage, _run(stage, checkpoint, tmp_path / "out", motion, "--frames", "0:4"))
    assert f"{motion}: shape coefficient betas[3] is 1e+30" in err and not (tmp_path / "out").exists()


def _long_amass(path, frames: int) -> None:
    """An AMASS clip of `frames` frames, deflated and written a block at a time: `poses` (frames, 156) float32
    (624 MB for a million frames, a few MB in the file), column 0 of frame i = (i mod 1000) / 1000."""
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED) as archive:
        for key, columns, dtype in (("poses", 156, "<f4"), ("trans", 3, "<f8")):
            with archive.open(f"{key}.npy", "w", force_zip64=True) as member:
                np.lib.format.write_array_header_1_0(member, {"descr": dtype, "fortran_order": False,
                                                              "shape": (frames, columns)})
                for start in range(0, frames, 50_000):
                    rows = np.zeros((min(50_000, frames - start), columns), dtype=dtype)
                    if key == "poses":
                        rows[:, 0] = (np.arange(start, start + len(rows)) % 1000) / 1000
                    member.write(rows.tobytes())
        with archive.open("mocap_framerate.npy", "w") as member:
            np.save(member, np.array(120.0))


def test_two_frames_of_a_million_frame_motion_are_read_alone_and_all_of_it_is_refused(checkpoint, tmp_path,  # noqa: F811
                                                                                       capsys):
    motion = tmp_path / "long.npz"
    _long_amass(motion, 1_000_000)
    with address_space_limit(GIB // 2):  # reading the whole motion took 3.7 GB
        assert run_cli(export_main, _run("export", checkpoint, tmp_path / "two", str(motion), "--frames", "0:2")) == 0
        for stage in STAGES:  # all of it: refused from the file's headers before anything is read
            err = _refused(capsys, stage, _run(stage, checkpoint, tmp_path / stage, str(motion)))
            assert f"{motion}: 1,000,000 frames selected" in err and not (tmp_path / stage).exists()
    assert sorted(p.name for p in (tmp_path / "two").glob("frame_*")) == ["frame_000000.ply", "frame_000001.ply"]
    clip = read_motion(motion, frames=slice(999_001, 999_999, 499))
    np.testing.assert_array_equal(clip.frames, [999_001, 999_500])
    np.testing.assert_allclose(clip.full_pose[:, 0, 0], [0.001, 0.5], rtol=1e-6)
    assert clip.fps == 120.0 / 499


@pytest.mark.parametrize("compression", [zipfile.ZIP_STORED, zipfile.ZIP_DEFLATED])
@pytest.mark.parametrize("rows", [range(0, 37), range(5, 6), range(3, 37, 4), range(36, 37), range(1, 30, 13)])
def test_rows_read_alone_equal_numpys_slice(tmp_path, monkeypatch, compression, rows):
    monkeypatch.setattr(npz, "ROW_BLOCK_BYTES", 50)  # blocks of 2 rows of 24 bytes: every block boundary is met
    rng = np.random.default_rng(0)
    arrays = {"frames": rng.normal(size=(37, 2, 3)), "other": rng.normal(size=(37, 2)), "scalar": np.array(4.0),
              "fortran": np.asfortranarray(rng.normal(size=(37, 2)))}
    path = tmp_path / "a.npz"
    with zipfile.ZipFile(path, "w", compression=compression) as archive:
        for key, value in arrays.items():
            with archive.open(f"{key}.npy", "w") as member:
                np.lib.format.write_array(member, value)
    read = npz.read_npz_rows(path, ValueError, "x", list(arrays), ("frames", "scalar", "fortran"), 37, rows)
    for key in ("frames", "fortran"):  # rows apart in a Fortran-order file: the whole member read, then sliced
        np.testing.assert_array_equal(read[key], arrays[key][rows.start:rows.stop:rows.step])
    for key in ("other", "scalar"):  # not a row member; no first dimension
        np.testing.assert_array_equal(read[key], arrays[key])
    with pytest.raises(ValueError, match="'frames' at 37 rows of 48 bytes is more than the 100 bytes"):
        npz.read_npz_rows(path, ValueError, "x", ["frames"], ["frames"], 37, range(37), max_bytes=100)


def test_a_frame_step_that_slows_the_video_below_the_bound_is_refused(checkpoint, tmp_path, capsys):  # noqa: F811
    err = _refused(capsys, "animate", _run("animate", checkpoint, tmp_path / "out", str(DEMO_MOTION), "--frames",
                                           "0:144:500"))  # 30 fps / 500: FFmpeg's VP9 cannot open below ~0.1 fps
    assert f"{DEMO_MOTION}: with --frames 0:144:500 the video would play at 0.06 fps" in err
    assert not (tmp_path / "out").exists()
    assert run_cli(animate_main, _run("animate", checkpoint, tmp_path / "out", str(DEMO_MOTION), "--frames",
                                      "0:144:500", "--fps", "2")) == 0  # resampled to a playable rate

"""What this machine has and lacks for a compute preset and a dataset: one line per check, `ok`, `warn` or
`missing`, with what to do (`pig doctor`).

Checks: torch and its CUDA build; gsplat's CUDA extension (prebuilt or in the JIT cache: found on disk and loaded
in a child process, never compiled here); nvcc for gsplat's first-call compile; the metric weights present and
checksummed (pig.metrics.weight_files); the body model; free disk at the results folder against an estimate of
what the preset and dataset write (`estimate_disk`). A check is `missing` only where the preset or dataset needs
what it lacks: the GPU stack where the preset gives a job a GPU, the LPIPS loss's weights where the fit uses them,
the SMPL-X model for a real capture, the disk. Metric weights for the evaluation alone are a `warn` (their
columns are n/a without them).
"""
from __future__ import annotations

import functools
import glob
import importlib.metadata
import importlib.util
import os
import re
import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pig.avatar.config import AvatarConfig
from pig.avatar.fit_config import FitConfig
from pig.avatar.plan import HELD_OUT, Protocol, SplitSize
from pig.config import ConfigError, config_dirs, from_dict, load_section, load_yaml, named_config
from pig.data.formats import FORMATS, subject_path
from pig.data.raw import CaptureError
from pig.data.rectify import output_size
from pig.data.splits import SplitConfig, make_split
from pig.data.synthetic.config import SyntheticConfig
from pig.data.thuman4 import IMAGE_SUFFIXES, read_calibration
from pig.field.latent_grid import FieldConfig
from pig.metrics.weight_files import LPIPS_FILES, by_name, status
from pig.stages.evaluate import EvaluateConfig
from pig.stages.preprocess import PreprocessConfig

VERDICTS = ("ok", "warn", "missing")
LOSS_USE = "fit's LPIPS loss"
GSPLAT_JIT_NAME = "gsplat_cuda"  # gsplat 1.5.3's JIT extension (gsplat/cuda/_backend.py)
LOAD_TIMEOUT_S = 120
CUDA_DEFAULT = Path("/usr/local/cuda")  # torch's extension builder's last guess of CUDA_HOME


@dataclass
class Check:
    name: str
    verdict: str  # one of VERDICTS
    detail: str  # what was found, and what to do where it is not ok


def line(check: Check) -> str:
    return f"{check.verdict:<8}{check.name:<12}{check.detail}"


def needs_gpu(preset: dict[str, Any]) -> bool:
    """Whether the preset's `resources:` section gives any job a GPU (a rule's entry or `default`)."""
    section = preset.get("resources") or {}
    return any(isinstance(entry, dict) and (entry.get("gpu") or 0) > 0 for entry in section.values())


# --- torch, gsplat, nvcc ---------------------------------------------------------------------------------------

def check_torch(gpu: bool) -> Check:
    import torch

    build = f"CUDA {torch.version.cuda} build" if torch.version.cuda else "CPU-only build (no CUDA)"
    if torch.cuda.is_available():
        names = ", ".join(torch.cuda.get_device_name(i) for i in range(torch.cuda.device_count()))
        return Check("torch", "ok", f"{torch.__version__}, {build}, GPUs: {names}")
    if not gpu:
        return Check("torch", "ok", f"{torch.__version__}, {build}, no GPU in use: this preset runs on the CPU")
    if torch.version.cuda is None:
        why = "install torch's CUDA build (pip install torch --index-url https://download.pytorch.org/whl/cu128)"
    else:
        why = "no CUDA GPU is visible (check nvidia-smi, the driver and CUDA_VISIBLE_DEVICES)"
    return Check("torch", "missing", f"{torch.__version__}, {build}; the preset runs jobs on a GPU: {why}")


def gsplat_extensions() -> tuple[str | None, list[Path]]:
    """(gsplat's version or None when not installed, its compiled CUDA extensions on disk) without importing gsplat:
    the prebuilt `gsplat/csrc*.so` of a wheel built with its CUDA code, then the JIT build that gsplat 1.5.3 loads
    from torch's extension folder: $TORCH_EXTENSIONS_DIR/gsplat_cuda, else
    <torch's cache>/torch_extensions/py<XY>_cu<NNN>/gsplat_cuda (torch.utils.cpp_extension._get_build_directory's
    folder, here computed, since that function creates it)."""
    spec = importlib.util.find_spec("gsplat")
    if spec is None or spec.origin is None:
        return None, []
    version = importlib.metadata.version("gsplat")
    found = [Path(p) for p in sorted(glob.glob(str(Path(spec.origin).parent / "csrc*.so")))]
    jit = jit_folder()
    if jit is not None and (jit / f"{GSPLAT_JIT_NAME}.so").is_file():
        found.append(jit / f"{GSPLAT_JIT_NAME}.so")
    return version, found


def jit_folder() -> Path | None:
    """Where torch builds and loads the JIT extension gsplat_cuda; None for a torch without CUDA."""
    import torch
    from torch.utils.cpp_extension import get_default_build_root

    root = os.environ.get("TORCH_EXTENSIONS_DIR")
    if root is None:
        if torch.version.cuda is None:
            return None
        build = f"py{sys.version_info.major}{sys.version_info.minor}{getattr(sys, 'abiflags', '')}_" \
                f"cu{torch.version.cuda.replace('.', '')}"
        root = os.path.join(get_default_build_root(), build)
    return Path(root) / GSPLAT_JIT_NAME


def loads(path: Path) -> str:
    """'' when the compiled extension at `path` loads (in a child process: a broken build can crash its loader),
    else the loader's last error line. Asked once per file and modification time (gsplat's and nvcc's checks)."""
    return _loads(str(path), path.stat().st_mtime_ns)


@functools.cache
def _loads(path: str, mtime_ns: int) -> str:
    module = Path(path).name.split(".")[0]
    code = ("import importlib.util, sys, torch; "
            "spec = importlib.util.spec_from_file_location(sys.argv[1], sys.argv[2]); "
            "spec.loader.exec_module(importlib.util.module_from_spec(spec))")
    try:
        done = subprocess.run([sys.executable, "-c", code, module, path], capture_output=True, text=True,
                              timeout=LOAD_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        return f"loading it took over {LOAD_TIMEOUT_S} s"
    if done.returncode == 0:
        return ""
    lines = [s for s in done.stderr.strip().splitlines() if s.strip()]
    return lines[-1] if lines else f"exit status {done.returncode}"


def nvcc_version() -> tuple[Path | None, str | None]:
    """(nvcc's path, its release such as '12.8') as torch's extension builder and gsplat find it: in $CUDA_HOME or
    $CUDA_PATH, else on PATH, else in /usr/local/cuda; (None, None) without one."""
    home = os.environ.get("CUDA_HOME") or os.environ.get("CUDA_PATH")
    on_path = shutil.which("nvcc")
    candidates = [Path(home) / "bin" / "nvcc"] if home else []
    candidates += [Path(on_path)] if on_path else []  # gsplat calls `nvcc` on PATH where CUDA_HOME has none
    candidates += [] if home else [CUDA_DEFAULT / "bin" / "nvcc"]
    path = next((p for p in candidates if p.is_file()), None)
    if path is None:
        return None, None
    try:
        text = subprocess.run([str(path), "--version"], capture_output=True, text=True, timeout=30).stdout
    except (OSError, subprocess.TimeoutExpired):
        return path, None
    match = re.search(r"release (\d+\.\d+)", text)
    return path, match.group(1) if match else None


def check_gsplat(gpu: bool) -> Check:
    version, built = gsplat_extensions()
    if version is None:
        verdict = "missing" if gpu else "warn"
        return Check("gsplat", verdict, "not installed (pip install gsplat==1.5.3); the CPU compositor renders "
                                        "without it, GPU jobs need it")
    failures = []
    for path in built:
        error = loads(path)
        if not error:
            return Check("gsplat", "ok", f"{version}, CUDA extension built: {path} (loads)")
        failures.append(f"{path} does not load ({error})")
    if not gpu:
        state = "; ".join(failures) if failures else "CUDA extension not built"
        return Check("gsplat", "ok", f"{version}, {state}; not needed: this preset renders on the CPU")
    nvcc, _ = nvcc_version()
    folder = jit_folder()
    looked = f"looked in {folder}" if folder is not None else "torch has no CUDA build to compile it for"
    state = "; ".join(failures) if failures else f"CUDA extension not built ({looked})"
    if nvcc is not None:
        return Check("gsplat", "warn", f"{version}, {state}: its first GPU call compiles it with {nvcc} (minutes, "
                                       f"once; cached for later runs)")
    return Check("gsplat", "missing", f"{version}, {state}, and no nvcc to compile it: install the CUDA toolkit "
                                      "(nvcc) matching torch's CUDA build")


def check_nvcc(gpu: bool) -> Check:
    import torch

    nvcc, release = nvcc_version()
    built = [path for path in gsplat_extensions()[1] if not loads(path)]
    if nvcc is None:
        if gpu and not built:
            return Check("nvcc", "missing", "not found (CUDA_HOME, PATH, /usr/local/cuda): gsplat compiles its CUDA "
                                            "code on its first GPU call and needs it; install the CUDA toolkit")
        why = "gsplat's CUDA extension is built and loads" if built else "this preset renders on the CPU"
        return Check("nvcc", "ok", f"not found; not needed: {why}")
    found = f"{nvcc}, release {release or 'unknown'}"
    if gpu and torch.version.cuda and release and release.split(".")[0] != torch.version.cuda.split(".")[0]:
        return Check("nvcc", "warn", f"{found}, but torch is built for CUDA {torch.version.cuda}: torch's "
                                     "extension builder refuses another major version; install a matching toolkit")
    return Check("nvcc", "ok", found)


# --- metric weights ----------------------------------------------------------------------------------------------

def check_weights(preset: dict[str, Any]) -> list[Check]:
    """The evaluation's LPIPS and FID files (warn when absent or bad: their columns are n/a), and the files of the
    fit's LPIPS term where the preset's fit uses pretrained ones (missing: the fit would leave the term out)."""
    evaluate = load_section(preset, "evaluate", EvaluateConfig)
    fit = load_section(preset, "fit", FitConfig)
    backbone, linear = LPIPS_FILES[evaluate.lpips_net]
    rows = [(backbone, evaluate.lpips_backbone_weights, "evaluation"),
            (linear, evaluate.lpips_linear_weights, "evaluation"),
            ("inception", evaluate.inception_weights, "evaluation")]
    if fit.weight_lpips > 0 and fit.lpips_weights == "pretrained":
        backbone, linear = LPIPS_FILES[fit.lpips_net]
        rows += [(backbone, fit.lpips_backbone_weights, LOSS_USE), (linear, fit.lpips_linear_weights, LOSS_USE)]
    uses: dict[tuple[str, str | None], list[str]] = {}  # one check per file and configured path
    for name, configured, use in rows:
        uses.setdefault((name, configured), []).append(use)
    checks = []
    for (name, configured), used_by in uses.items():
        found = status(by_name([name])[0], configured=configured)
        needed = LOSS_USE in used_by
        own = configured is not None and found.path is not None  # the user's own weights, loaded as they are
        if found.ok:
            verdict, consequence = "ok", ""
        elif own:
            verdict, consequence = "warn", " (a configured file, used as it is)"
        elif needed and found.checksum in ("-", "bad"):
            verdict, consequence = "missing", "; the fit would leave its LPIPS term out"
        else:
            verdict, consequence = "warn", "; its columns would be n/a" if not needed else ""
        detail = f"{name} for the {' and '.join(used_by)}: {found.verdict()}{consequence}"
        checks.append(Check("weights", verdict, detail))
    return checks


# --- body model --------------------------------------------------------------------------------------------------

def check_body_model(preset: dict[str, Any], dataset: dict[str, Any], source: str) -> Check:
    """A generated dataset brings its own body (the procedural stand-in, or `synthetic.body_model`); a real capture
    needs the SMPL-X model file its fits were made with, named by the dataset YAML's `body_model`."""
    if dataset.get("generated"):
        configured = load_section(preset, "synthetic", SyntheticConfig).body_model
        if configured is None:
            return Check("body", "ok", f"{dataset.get('name')}: the procedural stand-in, no SMPL-X file needed "
                                       f"(the real captures need one: {', '.join(real_datasets()) or 'none named'})")
        if Path(configured).is_file():
            return Check("body", "ok", f"{dataset.get('name')}: SMPL-X model {configured} (synthetic.body_model)")
        return Check("body", "missing", f"synthetic.body_model {configured} does not exist; unset it for the "
                                        "procedural stand-in")
    body = dataset.get("body_model")
    if body and Path(body).is_file():
        return Check("body", "ok", f"{dataset.get('name')}: SMPL-X model {body}")
    found = f"{body} does not exist" if body else "it is not set"
    return Check("body", "missing", f"{dataset.get('name')}: `body_model` in {source} must name the SMPL-X model file "
                                    f"({found}); download SMPLX_NEUTRAL.npz (licensed, smpl-x.is.tue.mpg.de), put it "
                                    "e.g. at data/body_models/SMPLX_NEUTRAL.npz and set `body_model:` to that path")


def real_datasets() -> list[str]:
    """The datasets named in config/datasets/ that are real captures (not generated), which need an SMPL-X file."""
    names = {path.stem for folder in config_dirs("datasets") for path in folder.glob("*.yaml")}
    return sorted(name for name in names if not load_yaml(named_config("datasets", name)).get("generated", False))


# --- disk --------------------------------------------------------------------------------------------------------

# Bytes per pixel of a view as the pipeline writes it, from benchmarks/NOTES.md ("On-disk encoding of the
# preprocessed capture": 1330 x 1150 views, subject on 10.3 % of the pixels; "Render storage": PNG chunks).
JPEG_BPP = 146e3 / (1330 * 1150)  # training views, JPEG q95 4:4:4
PNG_BPP = 332e3 / (1330 * 1150)  # held-out views, PNG level 1
MASK_BPP = 6.6e3 / (1330 * 1150)  # 1-bit PNG masks
RENDER_BPP = 12.0e3 / (256 * 256)  # rendered views, PNG chunks of 16 frames (264 KB at 1330 x 1150: 0.17)
# The generator's raw views (JPEG image and mask) and its true meshes per frame, measured on the default run
# (benchmarks/NOTES.md, "Disk written by the default run").
RAW_BPP = (3_468_776 + 2_354_433) / (288 * 256 * 256)
MESH_BYTES_PER_FRAME = 4_477_275 / 24
STANDIN_BODY_BYTES = 2_619_455
TRACK_BYTES = 16  # a splat's centre (3 float32) and opacity per rendered frame (the render's splats.npz)
ANCHOR_BYTES = 104  # an anchor's canonical frame, attachment, positions and their Adam moments in a checkpoint
PARAMETER_BYTES = 12  # a float32 parameter and its two Adam moments
# The byte rates vary with the subject's share of the frame and its texture: a quarter more than the formula (on the
# default run its images took 1.9x the capture's rates, its renders 1.2x, the fit's transient second checkpoint
# never came: 116 MB estimated against 73 MB written; benchmarks/NOTES.md).
MARGIN = 1.25
SMALL_FILES = 1e6  # per run: logs, metrics, the loss curve, montages


@dataclass
class Geometry:
    """A dataset's views as preprocess reads them: camera names with their (width, height), and frame ids."""

    cameras: dict[str, tuple[int, int]]
    frames: list[int]
    how: str


def nominal_geometry(preset: dict[str, Any], dataset: dict[str, Any]) -> Geometry | None:
    """The generated capture's views from the preset's `synthetic` section; a THuman4-layout capture's from its
    first subject's calibration.json and image count where present; THuman4 and DNA-Rendering from FORMATS.md
    (24 cameras x 2500 frames at 1330 x 1150; 48 cameras at 2448 x 2048 and 12 at 4096 x 3000 x 225 frames, the
    frames a co-author's evaluation uses); an EasyMocap, ActorsHQ or AvatarReX capture's from its first subject's
    calibration and body parameters; None for anything else."""
    if dataset.get("generated"):
        cfg = load_section(preset, "synthetic", SyntheticConfig)
        return Geometry({f"cam{i:02d}": (cfg.width, cfg.height) for i in range(cfg.cameras)}, list(range(cfg.frames)),
                        "the preset's synthetic section")
    subjects = dataset.get("subjects") or []
    try:
        root = Path(dataset.get("root", "")) / subject_path(dataset, str(subjects[0]), "dataset") if subjects else None
    except CaptureError:  # preprocess names the bad `subject_paths` entry
        root = None
    fmt = FORMATS.get(dataset.get("format"))
    if fmt is not None and fmt.geometry is not None and root is not None and root.is_dir():
        try:  # a file the reader refuses gives no sizes here; preprocess names what is wrong with it
            cameras, frames = fmt.geometry(root, dataset.get("reader") or {})
        except (CaptureError, OSError):
            frames = []
        if frames:
            return Geometry(cameras, frames, f"{root}'s calibration and body parameters")
    if dataset.get("format") == "thuman4" and root is not None and (root / "calibration.json").is_file():
        try:  # a file the reader refuses gives no sizes here; preprocess names what is wrong with it
            cameras = {name: (cam.width, cam.height) for name, cam in read_calibration(root / "calibration.json").items()}
            first = root / "images" / next(iter(cameras))
            frames = sorted(int(p.stem) for p in first.iterdir()
                            if p.suffix.lower() in IMAGE_SUFFIXES and p.stem.isdigit()) if first.is_dir() else []
        except (CaptureError, OSError):
            frames = []
        if frames:
            return Geometry(cameras, frames, f"{root}'s calibration and images")
    if dataset.get("name") == "thuman4":
        return Geometry({f"cam{i:02d}": (1330, 1150) for i in range(24)}, list(range(2500)), "THuman4's sizes")
    if dataset.get("name") == "dna":
        cameras = {str(i): (2448, 2048) if i < 48 else (4096, 3000) for i in range(60)}
        return Geometry(cameras, list(range(225)), "DNA-Rendering's sizes")
    return None


def nominal_views(preset: dict[str, Any], dataset: dict[str, Any]) \
        -> tuple[Geometry, dict[str, int], dict[str, dict[str, list]]] | None:
    """(nominal_geometry, each camera's pixels after preprocessing (the preset's scale and max_side for the
    dataset), the protocol's split of those cameras and frames), or None without sizes."""
    geometry = nominal_geometry(preset, dataset)
    if geometry is None:
        return None
    prep = load_section(preset, "preprocess", PreprocessConfig)
    overrides = prep.datasets.get(dataset.get("name"), {})
    scale, max_side = overrides.get("scale", prep.scale), overrides.get("max_side", prep.max_side)
    pixels = {c: output_size(w, h, scale, max_side) for c, (w, h) in geometry.cameras.items()}
    split_cfg = from_dict(SplitConfig, dict(dataset.get("split") or {}), "dataset split")
    split = make_split(list(geometry.cameras), geometry.frames, split_cfg, str((dataset.get("subjects") or ["?"])[0]))
    return geometry, {c: w * h for c, (w, h) in pixels.items()}, split


def nominal_protocol(preset: dict[str, Any], dataset: dict[str, Any]) -> Protocol | None:
    """One subject's held-out splits and capture from the dataset's nominal sizes (pig plan), or None without
    sizes; the first subject's split stands for every subject's."""
    views = nominal_views(preset, dataset)
    if views is None:
        return None
    geometry, pixels, split = views
    sizes = {}
    for name in HELD_OUT:
        cameras, frames = split[name]["cameras"], len(split[name]["frames"])
        sizes[name] = SplitSize(frames, len(cameras) * frames, sum(pixels[c] for c in cameras) / len(cameras) / 1e6)
    written = {}
    for part in split.values():
        for camera in part["cameras"]:
            written[camera] = written.get(camera, 0) + len(part["frames"])
    capture_views = sum(written.values())
    raw = sum(count * geometry.cameras[c][0] * geometry.cameras[c][1] for c, count in written.items())
    return Protocol(sizes, capture_views, raw / capture_views / 1e6)


@dataclass
class DiskEstimate:
    total: float
    parts: dict[str, float]  # per subject: raw (generated data only), capture, fit, renders
    subjects: int
    how: str


def estimate_disk(preset: dict[str, Any], dataset: dict[str, Any], variants: int = 1) -> DiskEstimate | None:
    """Bytes the default target writes for the dataset's subjects with `variants` fits each, or None without sizes.

    Per subject, with W x H each view's size after preprocessing (scale, max_side):
      raw (generated only) = views x W H x RAW_BPP + frames x MESH_BYTES_PER_FRAME + STANDIN_BODY_BYTES
      capture = sum over training views W H (JPEG_BPP or PNG_BPP) + held-out views W H PNG_BPP + all views W H
                MASK_BPP, + the true meshes and body model for a generated capture
      fit (per variant) = 2 x checkpoint (the old one stays until the new one is in place), checkpoint =
                PARAMETER_BYTES x (features x sum of resolution^3 + 2 x hidden_layers x hidden_width^2)
                + ANCHOR_BYTES x anchors + the body model's bytes
      renders (per variant) = sum over splits and LODs of (views x W H x RENDER_BPP + frames x anchors at the LOD x
                TRACK_BYTES), anchors at LOD l = anchors / 2^(levels - 1 - l)
    each times MARGIN, + SMALL_FILES per run.
    """
    views = nominal_views(preset, dataset)
    if views is None:
        return None
    geometry, pixels, split = views
    prep = load_section(preset, "preprocess", PreprocessConfig)
    area = {name: sum(pixels[c] for c in part["cameras"]) * len(part["frames"]) for name, part in split.items()}
    train_bpp = JPEG_BPP if prep.train_encoding == "jpeg" else PNG_BPP
    heldout_bpp = PNG_BPP if prep.heldout_encoding == "png" else JPEG_BPP
    generated = bool(dataset.get("generated"))
    frames = len(geometry.frames)
    extras = frames * MESH_BYTES_PER_FRAME + STANDIN_BODY_BYTES if generated else 0.0
    parts = {}
    if generated:
        parts["raw"] = sum(w * h for w, h in geometry.cameras.values()) * frames * RAW_BPP + extras
    views = area["train"] + area["novel_view"] + area["novel_pose"]
    parts["capture"] = area["train"] * train_bpp + (area["novel_view"] + area["novel_pose"]) * heldout_bpp \
        + views * MASK_BPP + extras
    avatar = load_section(preset, "avatar", AvatarConfig)
    grid = load_section(preset, "field", FieldConfig)
    body_bytes = STANDIN_BODY_BYTES if generated or not dataset.get("body_model") or \
        not Path(dataset["body_model"]).is_file() else Path(dataset["body_model"]).stat().st_size
    checkpoint = PARAMETER_BYTES * (grid.features * sum(r ** 3 for r in grid.resolutions)
                                    + 2 * avatar.hidden_layers * avatar.hidden_width ** 2) \
        + ANCHOR_BYTES * avatar.num_anchors + body_bytes
    parts["fit"] = variants * 2 * checkpoint
    anchors = sum(avatar.num_anchors / 2 ** (avatar.levels - 1 - level) for level in range(avatar.levels))
    heldout = [split["novel_view"], split["novel_pose"]]
    renders = avatar.levels * (area["novel_view"] + area["novel_pose"]) * RENDER_BPP \
        + sum(len(part["frames"]) for part in heldout) * anchors * TRACK_BYTES
    parts["renders"] = variants * renders
    parts = {name: MARGIN * size for name, size in parts.items()}
    subjects = len(dataset.get("subjects") or [1])
    total = subjects * (sum(parts.values()) + variants * SMALL_FILES)
    return DiskEstimate(total, parts, subjects, geometry.how)


def free_bytes(folder: Path) -> tuple[Path, int]:
    """(the folder or its nearest existing parent, its free bytes)."""
    folder = Path(folder).absolute()
    while not folder.exists() and folder != folder.parent:
        folder = folder.parent
    return folder, shutil.disk_usage(folder).free


def check_disk(preset: dict[str, Any], dataset: dict[str, Any], results: Path) -> Check:
    where, free = free_bytes(results)
    estimate = estimate_disk(preset, dataset)
    if estimate is None:
        return Check("disk", "warn", f"{gb(free)} free at {where}; no size estimate for dataset "
                                     f"{dataset.get('name')!r} (its view sizes are unknown until preprocessed)")
    parts = ", ".join(f"{name} {gb(size)}" for name, size in estimate.parts.items())
    need = f"the default target writes up to ~{gb(estimate.total)} ({estimate.subjects} subject(s) x ({parts}); " \
           f"sizes from {estimate.how})"
    if free < estimate.total:
        return Check("disk", "missing", f"{gb(free)} free at {where}, {need}: free space or choose --results on "
                                        "another disk (snakemake --directory)")
    return Check("disk", "ok", f"{gb(free)} free at {where}; {need}")


def gb(size: float) -> str:
    return f"{size / 1e9:,.1f} GB" if size >= 1e9 else f"{size / 1e6:,.1f} MB"


# --- all of it ---------------------------------------------------------------------------------------------------

def load_dataset(name_or_path: str) -> tuple[dict[str, Any], str]:
    """(the dataset YAML, its path) for a name in config/datasets/ or a path to a YAML file."""
    path = Path(name_or_path) if Path(name_or_path).suffix in (".yaml", ".yml") else named_config("datasets",
                                                                                                     name_or_path)
    data = load_yaml(path)
    if "name" not in data:
        raise ConfigError(f"{path}: expected a dataset YAML with `name`, `format` and `subjects`")
    return data, str(path)


def run_checks(preset: dict[str, Any], dataset: str, results: Path) -> list[Check]:
    """Every check for `preset` (a loaded preset) and `dataset` (a name in config/datasets/ or a YAML path)."""
    data, source = load_dataset(dataset)
    gpu = needs_gpu(preset)
    return [check_torch(gpu), check_gsplat(gpu), check_nvcc(gpu), *check_weights(preset),
            check_body_model(preset, data, source), check_disk(preset, data, results)]


def report(checks: list[Check], preset: dict[str, Any], dataset: str) -> str:
    """The screen: a heading, one line per check, and the verdict."""
    missing = [c.name for c in checks if c.verdict == "missing"]
    head = f"pig doctor: preset {preset.get('_path')} ({'GPU jobs' if needs_gpu(preset) else 'CPU only'}), " \
           f"dataset {dataset}"
    tail = f"missing for this preset and dataset: {', '.join(dict.fromkeys(missing))}" if missing else \
        "everything this preset and dataset need is here"
    return "\n".join([head, *map(line, checks), tail])

"""The metric networks' weight files, each with its published URL and SHA-256: where each is looked up, whether
it is there and intact, and the project's only network use, an explicit checksummed fetch (`pig weights --fetch`).

Imports no torch (the workflow checks the LPIPS loss's files while it builds its DAG): `hub_checkpoints` is the
torch-free twin of pig.metrics.weights.hub_checkpoints, and a test holds the two equal.
"""
from __future__ import annotations

import hashlib
import http.client
import importlib.util
import os
import time
import urllib.error
import urllib.request
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path

from pig.progress import progress_bar
from pig._io import _still_ours, create_temporary, file_sha256


@dataclass(frozen=True)
class WeightFile:
    name: str  # what `pig weights --only` takes
    filename: str  # as published; the metrics look it up under this name
    url: str
    sha256: str | None  # None: no source confirmed it, and the fetch refuses the file
    size: int | None  # bytes as published
    source: str  # where the SHA-256 was confirmed
    used_by: str
    in_lpips_package: bool = False  # the lpips package ships it: its weights/v0.1 folder is looked up too


TORCHVISION = "https://download.pytorch.org/models/"
LPIPS_REPO = "https://raw.githubusercontent.com/richzhang/PerceptualSimilarity/master/lpips/weights/v0.1/"
# The SHA-256s: torchvision's file names carry their first 8 hex digits (its hub download checks that prefix); the
# full values and sizes agree across many public manifests that pin these files. The lpips linear layers' were
# computed here from the files in richzhang/PerceptualSimilarity (commit 082bb24f, master, December 2023) and in
# PyPI's lpips-0.1.4 wheel: the same bytes.
WEIGHT_FILES = (
    WeightFile("alexnet", "alexnet-owt-7be5be79.pth", TORCHVISION + "alexnet-owt-7be5be79.pth",
               "7be5be791159472b1fbf3c69796f7cb30dca7ad8466c2df70058c37116cdee02", 244_408_911,
               "torchvision (prefix in the name); full value in public manifests pinning it",
               "LPIPS alex backbone (evaluation, cpu-demo and test presets)"),
    WeightFile("vgg16", "vgg16-397923af.pth", TORCHVISION + "vgg16-397923af.pth",
               "397923af8e79cdbb6a7127f12361acd7a2f83e06b05044ddf496e83de57a5bf0", 553_433_881,
               "torchvision (prefix in the name); full value in public manifests pinning it",
               "LPIPS vgg backbone (evaluation and the fit's LPIPS loss, paper preset)"),
    WeightFile("lpips-alex", "alex.pth", LPIPS_REPO + "alex.pth",
               "df73285e35b22355a2df87cdb6b70b343713b667eddbda73e1977e0c860835c0", 6_009,
               "richzhang/PerceptualSimilarity lpips/weights/v0.1/alex.pth and the lpips 0.1.4 wheel, hashed",
               "LPIPS alex linear layers (evaluation, cpu-demo and test presets)", in_lpips_package=True),
    WeightFile("lpips-vgg", "vgg.pth", LPIPS_REPO + "vgg.pth",
               "a78928a0af1e5f0fcb1f3b9e8f8c3a2a5a3de244d830ad5c1feddc79b8432868", 7_289,
               "richzhang/PerceptualSimilarity lpips/weights/v0.1/vgg.pth and the lpips 0.1.4 wheel, hashed",
               "LPIPS vgg linear layers (evaluation and the fit's LPIPS loss, paper preset)", in_lpips_package=True),
    WeightFile("inception", "inception-2015-12-05.pt",
               "https://nvlabs-fi-cdn.nvidia.com/stylegan2-ada-pytorch/pretrained/metrics/inception-2015-12-05.pt",
               "f58cb9b6ec323ed63459aa4fb441fe750cfe39fafad6da5cb504a16f19e958f4", 95_607_719,
               "crowsonkb/k-diffusion k_diffusion/evaluation.py (the digest its download checks)",
               "FID Inception network (evaluation)"),
)
# The files of each LPIPS backbone (pig.metrics.weights.TORCHVISION_FILES and LPIPS_LINEAR_FILES by name).
LPIPS_FILES = {"alex": ("alexnet", "lpips-alex"), "vgg": ("vgg16", "lpips-vgg")}
FETCH_COMMAND = "pig weights --fetch"
CHUNK = 1 << 20
# A download slower than this over a whole window is given up: a server or proxy that trickles would otherwise hold
# the fetch for hours (one byte a second: years for VGG16). At the floor VGG16's 553 MB takes about 3 hours.
MIN_BYTES_PER_S = 50_000
RATE_WINDOW_S = 60.0


class FetchError(OSError):
    """A weight file could not be fetched; the message names the file, the URL and why. Nothing was replaced."""


def by_name(names: Iterable[str] | None = None) -> list[WeightFile]:
    """The table's entries named in `names` (all when None), in table order; an unknown name is an error."""
    if names is None:
        return list(WEIGHT_FILES)
    known = {f.name: f for f in WEIGHT_FILES}
    unknown = sorted(set(names) - set(known))
    if unknown:
        raise ValueError(f"unknown weight file name(s) {unknown}; expected some of {list(known)}")
    return [f for f in WEIGHT_FILES if f.name in set(names)]


def hub_checkpoints() -> Path:
    """torch.hub's checkpoint cache as torch finds it without a `set_dir`: $TORCH_HOME/hub/checkpoints, else
    $XDG_CACHE_HOME/torch/hub/checkpoints, else ~/.cache/torch/hub/checkpoints."""
    cache = os.getenv("XDG_CACHE_HOME", os.path.join("~", ".cache"))
    return Path(os.path.expanduser(os.getenv("TORCH_HOME", os.path.join(cache, "torch")))) / "hub" / "checkpoints"


def lpips_package_weights() -> Path | None:
    """The lpips package's `weights/v0.1` folder if the package is installed (it is not imported)."""
    spec = importlib.util.find_spec("lpips")
    if spec is None or spec.origin is None:
        return None
    return Path(spec.origin).parent / "weights" / "v0.1"


def candidates(entry: WeightFile, dest: Path | None = None, configured: str | Path | None = None) -> list[Path]:
    """Where `entry` is looked up, in order, as the metrics look it up: a configured path alone; else `dest`
    alone when given; else the torch hub cache, then the lpips package's folder for its linear layers."""
    if configured is not None:
        return [Path(configured).expanduser()]
    if dest is not None:
        return [Path(dest) / entry.filename]
    package = lpips_package_weights() if entry.in_lpips_package else None
    return [folder / entry.filename for folder in (hub_checkpoints(), package) if folder is not None]


@dataclass
class Status:
    entry: WeightFile
    searched: list[Path]
    path: Path | None  # the first existing candidate
    checksum: str  # "ok", "bad", "unknown" (no confirmed SHA-256 to check against) or "-" (missing)

    @property
    def ok(self) -> bool:
        return self.path is not None and self.checksum == "ok"

    def verdict(self) -> str:
        """One line: present or missing, the checksum, and where it was found or sought."""
        if self.path is None:
            return f"missing ({', '.join(map(str, self.searched))}); {FETCH_COMMAND} --only {self.entry.name}"
        if self.checksum == "bad":
            return f"checksum bad: {self.path} is not the published file; move it away, then {FETCH_COMMAND}"
        if self.checksum == "unknown":
            return f"present at {self.path}, checksum unknown (no confirmed SHA-256)"
        return f"present at {self.path}, checksum ok"


def status(entry: WeightFile, dest: Path | None = None, configured: str | Path | None = None) -> Status:
    """Whether `entry` is found where the metrics look for it (`candidates`), and whether its bytes hash to the
    published SHA-256: a file whose size differs from the published one is bad without being read; one of that
    size is read whole (~1 s for VGG16's 553 MB)."""
    searched = candidates(entry, dest, configured)
    path = next((p for p in searched if p.is_file()), None)
    if path is None:
        return Status(entry, searched, None, "-")
    if entry.sha256 is None:
        return Status(entry, searched, path, "unknown")
    if entry.size is not None and path.stat().st_size != entry.size:
        return Status(entry, searched, path, "bad")
    return Status(entry, searched, path, "ok" if file_sha256(path) == entry.sha256 else "bad")


def check_destination(dest_dir: Path) -> None:
    """FetchError unless `dest_dir` is a folder or can be made one (no file in its place or above it)."""
    dest_dir = Path(dest_dir)
    existing = next((p for p in (dest_dir, *dest_dir.parents) if os.path.lexists(p)), None)
    if existing is not None and not existing.is_dir():
        where = "is" if existing == dest_dir else f"lies under {existing}, which is"
        raise FetchError(f"{dest_dir}: {where} a file, not a folder; choose a folder to fetch into (--dest)")


def fetch(entry: WeightFile, dest_dir: Path, opener: Callable = urllib.request.urlopen, timeout: float = 60.0,
          report: Callable[[str], None] = print, clock: Callable[[], float] = time.monotonic,
          min_rate: float = MIN_BYTES_PER_S, window_s: float = RATE_WINDOW_S) -> Path:
    """Download `entry` into `dest_dir`: to a hidden temporary beside it (pig._io.create_temporary: made here,
    never through a planted link), SHA-256 checked, then linked into place under its published name (atomic, and
    never over a file already there). Returns the path; raises FetchError (the temporary removed) on a file without
    a confirmed SHA-256, a destination that is no writable folder, an HTTP or network error, no byte within
    `timeout` seconds, fewer than `min_rate` bytes a second over any `window_s` seconds by `clock`, a cut
    transfer or a checksum mismatch."""
    target = Path(dest_dir) / entry.filename
    if entry.sha256 is None:
        raise FetchError(f"{entry.filename}: no SHA-256 of it was confirmed from a source, so it is not fetched; "
                         f"download {entry.url} yourself, check it, and place it at {target}")
    check_destination(Path(dest_dir))
    if os.path.lexists(target):
        raise FetchError(f"{target}: already there; nothing fetched (move it away first to fetch it again)")
    try:
        tmp, fd = create_temporary(target)
    except OSError as err:
        raise FetchError(f"{target}: cannot write in its folder ({err.strerror or err}); choose a folder to fetch "
                         "into that this user can write (--dest); nothing was fetched") from None
    try:
        with os.fdopen(fd, "wb") as out:
            created = os.fstat(out.fileno())
            _download(entry, out, target, opener, timeout, report, clock, min_rate, window_s)
        try:
            _still_ours(tmp, created)
        except OSError as err:
            raise FetchError(f"{entry.filename}: {err}") from None
        _place(tmp, target)
    finally:
        tmp.unlink(missing_ok=True)
    return target


def _download(entry: WeightFile, out, target: Path, opener: Callable, timeout: float, report: Callable[[str], None],
              clock: Callable[[], float], min_rate: float, window_s: float) -> None:
    """Write `entry`'s download to the file `out` (of `target`) under `fetch`'s checks."""
    digest, received = hashlib.sha256(), 0
    try:
        with opener(entry.url, timeout=timeout) as response:
            length = response.headers.get("Content-Length")
            length = int(length) if length is not None and length.strip().isdigit() else None
            expected = length if length is not None else entry.size
            report(f"weights: fetching {entry.filename} ({_megabytes(expected)}) from {entry.url}; its SHA-256 "
                   f"from {entry.source}")
            window_start, window_bytes = clock(), 0
            with progress_bar(total=expected, unit="B", unit_scale=True, desc=entry.name, leave=False) as bar:
                # read1: whatever one socket read brings, so that a trickle comes back here to be timed
                for block in iter(lambda: response.read1(CHUNK), b""):
                    received += len(block)
                    if entry.size is not None and received > entry.size:  # a server that never stops sending
                        raise FetchError(f"{entry.filename}: download from {entry.url} sent more than the "
                                         f"{entry.size:,} bytes of the published file; stopped, nothing was kept")
                    digest.update(block)
                    try:
                        out.write(block)
                    except OSError as err:
                        raise FetchError(f"{target}: writing the download failed after {received:,} bytes "
                                         f"({err.strerror or err}); nothing was kept") from None
                    bar.update(len(block))
                    window_bytes += len(block)
                    elapsed = clock() - window_start
                    if elapsed >= window_s:
                        if window_bytes < min_rate * elapsed:
                            raise FetchError(
                                f"{entry.filename}: download from {entry.url} too slow: {window_bytes:,} bytes in the "
                                f"last {elapsed:.0f} s, below the floor of {min_rate / 1e3:,.0f} kB/s; given up after "
                                f"{received:,} of {_megabytes(expected)}, nothing was kept. Try again later, or "
                                f"download it by other means and place it at its path (sha256 {entry.sha256})")
                        window_start, window_bytes = clock(), 0
    except FetchError:
        raise
    except urllib.error.HTTPError as err:
        raise FetchError(f"{entry.filename}: HTTP {err.code} ({err.reason}) from {entry.url}") from None
    except (urllib.error.URLError, OSError, http.client.HTTPException) as err:  # refused, unreachable, cut off
        why = getattr(err, "reason", err)
        raise FetchError(f"{entry.filename}: download from {entry.url} failed after {received:,} bytes ({why})") \
            from None
    if length is not None and received != length:
        raise FetchError(f"{entry.filename}: download from {entry.url} was cut off at {received:,} of "
                         f"{length:,} bytes; nothing was kept")
    if digest.hexdigest() != entry.sha256:
        raise FetchError(f"{entry.filename}: SHA-256 of the download from {entry.url} is {digest.hexdigest()}, "
                         f"expected {entry.sha256}; the download was deleted, nothing was kept")


# FitConfig's defaults of the keys that decide the fit's LPIPS term (pig.avatar.fit_config; a test holds them equal):
# read from a preset's raw `fit` section here, where the workflow builds its DAG without torch.
LOSS_DEFAULTS = {"weight_lpips": 2.0, "lpips_net": "vgg", "lpips_weights": "pretrained", "lpips_backbone_weights": None,
                 "lpips_linear_weights": None}


def loss_weight_problems(fit: dict) -> list[str]:
    """One line per weight file that the fit's LPIPS term (Eq. 15) needs and lacks, missing or failing its checksum,
    for a preset's `fit` section `fit` (a raw mapping, variant overrides applied); [] when the term is off (weight
    0) or uses random weights, or has its files."""
    cfg = {**LOSS_DEFAULTS, **{key: fit[key] for key in LOSS_DEFAULTS if key in fit}}
    if cfg["weight_lpips"] <= 0 or cfg["lpips_weights"] != "pretrained" or cfg["lpips_net"] not in LPIPS_FILES:
        return []
    backbone, linear = LPIPS_FILES[cfg["lpips_net"]]
    problems = []
    for name, configured in ((backbone, cfg["lpips_backbone_weights"]), (linear, cfg["lpips_linear_weights"])):
        found = status(by_name([name])[0], configured=configured)
        # A configured file is the user's own (fine-tuned) weights, as the fit loads it: only its absence counts.
        if not found.ok and found.checksum != "unknown" and not (configured is not None and found.path is not None):
            problems.append(f"{name}: {found.verdict()}")
    return problems


def status_table(statuses: list[Status]) -> str:
    """Two lines per file: its name, file name, state (ok, missing, bad, unknown), published size and where it is
    (or the places it was sought); then what uses it."""
    rows = [("name", "file", "state", "size", "where")]
    for s in statuses:
        state = "missing" if s.path is None else s.checksum
        where = str(s.path) if s.path is not None else "not in " + ", ".join(map(str, s.searched))
        rows.append((s.entry.name, s.entry.filename, state, _megabytes(s.entry.size), where))
        rows.append(("", "", "", "", f"used by: {s.entry.used_by}"))
    widths = [max(len(row[i]) for row in rows) for i in range(4)]
    return "\n".join(("  ".join(cell.ljust(w) for cell, w in zip(row[:4], widths)) + "  " + row[4]).rstrip()
                     for row in rows)


def check_and_fetch(names: Iterable[str] | None = None, fetch_missing: bool = False, dest: Path | None = None,
                    opener: Callable = urllib.request.urlopen, report: Callable[[str], None] = print) -> bool:
    """`pig weights`: report each named file (all when None) as `status_table` does, looked up in `dest` or where
    the metrics look; with `fetch_missing`, download the missing ones into `dest` (default: the torch hub cache)
    first. A file that is present but bad is reported, never replaced. True when every named file is present with
    a good checksum at the end."""
    entries = by_name(names)
    failures = []
    if fetch_missing:
        folder = Path(dest) if dest is not None else hub_checkpoints()
        try:
            check_destination(folder)
        except FetchError as err:  # said once, not once per file
            failures.append(str(err))
            entries_to_fetch = []
        else:
            entries_to_fetch = entries
        for entry in entries_to_fetch:
            if not any(path.is_file() for path in candidates(entry, dest)):
                try:
                    report(f"weights: {entry.filename} ok, at {fetch(entry, folder, opener, report=report)}")
                except FetchError as err:
                    failures.append(str(err))
    statuses = [status(entry, dest) for entry in entries]
    report(status_table(statuses))
    for line in failures:
        report(f"weights: not fetched: {line}")
    for s in statuses:
        if s.path is not None and s.checksum == "bad":
            report(f"weights: {s.verdict()}")
    if not fetch_missing and any(s.path is None for s in statuses):
        report(f"weights: missing files are fetched (only by request, checksummed) with `{FETCH_COMMAND}`")
    return all(s.ok for s in statuses)


def _place(tmp: Path, target: Path) -> None:
    """Link `tmp` in as `target`: unlike a rename, a link never replaces a file that appeared meanwhile. Where
    the file system has no hard links, a rename after checking that `target` is still absent."""
    try:
        os.link(tmp, target)
        return
    except FileExistsError:
        pass
    except OSError:
        if not target.exists():
            os.rename(tmp, target)
            return
    raise FetchError(f"{target}: appeared while fetching; left as it is, the download deleted")


def _megabytes(size: int | None) -> str:
    if size is None:
        return "size unknown"
    return f"{size / 1e6:,.1f} MB" if size >= 1e6 else f"{size / 1e3:,.1f} kB"

"""Where the pretrained metric networks' weights are looked up on disk; nothing is downloaded here (`pig weights
--fetch`, pig.metrics.weight_files, is the one explicit, checksummed fetch).

Search order per file: a configured path, the torch hub cache ($TORCH_HOME/hub/checkpoints, by
default ~/.cache/torch/hub/checkpoints), then the lpips package's folder for its linear layers; never a folder
anyone can write (clean-fid's /tmp).
"""
from __future__ import annotations

from pathlib import Path

import torch

from pig.metrics.weight_files import LPIPS_FILES, by_name, lpips_package_weights  # noqa: F401 (re-exported)

# File names as torchvision, the lpips package and the StyleGAN/clean-fid metrics publish them: the weight table's.
TORCHVISION_FILES = {net: by_name([backbone])[0].filename for net, (backbone, _) in LPIPS_FILES.items()}
LPIPS_LINEAR_FILES = {net: by_name([linear])[0].filename for net, (_, linear) in LPIPS_FILES.items()}
INCEPTION_FILE = by_name(["inception"])[0].filename


class WeightsMissing(FileNotFoundError):
    """A metric network's weights are not on disk; the message says which file and where it was sought."""


def hub_checkpoints() -> Path:
    """The torch hub checkpoint cache, honouring $TORCH_HOME and $XDG_CACHE_HOME as torch does."""
    return Path(torch.hub.get_dir()) / "checkpoints"


def locate(filename: str, configured: str | Path | None, extra_dirs: list[Path | None], what: str) -> Path:
    """The first existing file among `configured` (if set, the only candidate) and the search dirs."""
    if configured is not None:
        path = Path(configured).expanduser()
        if path.is_file():
            return path
        raise WeightsMissing(f"{what}: configured weights file {path} does not exist (expected {filename})")
    candidates = [d / filename for d in [hub_checkpoints(), *extra_dirs] if d is not None]
    for path in candidates:
        if path.is_file():
            return path
    searched = ", ".join(str(p) for p in candidates)
    raise WeightsMissing(f"{what}: weights file {filename} not found (searched {searched}); place it there "
                         "(`pig weights --fetch`) or configure its path")


def load_state_dict(path: Path) -> dict[str, torch.Tensor]:
    """A tensor-only state_dict from a .pth file, with a clear error for anything else."""
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:  # torch raises several types for corrupt or non-tensor pickles
        raise WeightsMissing(f"{path}: not a readable PyTorch state_dict ({err})") from None
    if not isinstance(state, dict):
        raise WeightsMissing(f"{path}: expected a state_dict mapping, found {type(state).__name__}")
    return state

"""pig._io's atomic writers against planted links: a symbolic link at the name a writer's temporary would take
(or at a stage's lock file), pointing at a file or folder outside the destination, is never written through nor
renamed into place; the temporaries stay findable by `remove_orphans`.

The random part of the names is made predictable here (`pig._io._token`), so that links can be planted at the
names the writer tries first, and at the earlier fixed name `.{stem}.{pid}.tmp{suffix}`.
"""
from __future__ import annotations

import itertools
import json
import os
import subprocess
from pathlib import Path

import numpy as np
import pytest
import torch

import pig._io as io

PLANTED_TOKENS = ("00000000", "00000001", "00000002")


@pytest.fixture
def tokens(monkeypatch):
    """Random parts in a known order: the planted ones first, then fresh ones."""
    sequence = itertools.chain(PLANTED_TOKENS, (f"{i:08x}" for i in itertools.count(0xA0000000)))
    monkeypatch.setattr(io, "_token", lambda: next(sequence), raising=False)


def plant_file_links(path: Path, outside: Path) -> list[Path]:
    """Links to `outside` at the earlier fixed temporary name of `path` and at its first random names."""
    pid = os.getpid()
    names = [f".{path.stem}.{pid}.tmp{path.suffix}"] + [f".{path.stem}.{pid}.{t}.tmp{path.suffix}"
                                                        for t in PLANTED_TOKENS]
    path.parent.mkdir(parents=True, exist_ok=True)
    links = [path.with_name(name) for name in names]
    for link in links:
        link.symlink_to(outside)
    return links


def _save_tensor(path: Path) -> None:
    with io.atomic_path(path) as tmp:
        torch.save({"weights": torch.arange(4)}, tmp)


def _save_npz(path: Path) -> None:
    with io.atomic_path(path) as tmp:
        np.savez(tmp, values=np.arange(4))


WRITERS = {
    "notes.txt": lambda path: io.write_text(path, "written by the writer\n"),
    "summary.json": lambda path: io.write_json(path, {"psnr": 30.0}),
    "frame.png": lambda path: io.write_png(path, np.full((4, 5, 3), 0.5)),
    "avatar.pt": _save_tensor,
    "track.npz": _save_npz,
}


@pytest.mark.parametrize("name", sorted(WRITERS))
def test_a_link_planted_at_a_temporary_name_is_not_written_through(tmp_path, tokens, name):
    outside = tmp_path / "elsewhere" / "precious.bin"
    outside.parent.mkdir()
    outside.write_bytes(b"not to be touched")
    path = tmp_path / "out" / name
    links = plant_file_links(path, outside)
    WRITERS[name](path)
    assert outside.read_bytes() == b"not to be touched"
    assert path.is_file() and not path.is_symlink() and not path.samefile(outside)
    assert path.stat().st_size > 0
    if name == "summary.json":
        assert json.loads(path.read_text()) == {"psnr": 30.0}
    assert all(link.is_symlink() for link in links)  # left as they were: not the writer's to remove


def test_a_link_planted_at_a_folder_temporary_name_is_not_built_in(tmp_path, tokens):
    """atomic_dir builds in a folder it made itself, and sets the folder it replaces aside under a fresh name."""
    outside = tmp_path / "elsewhere"
    outside.mkdir()
    (outside / "keep.txt").write_text("theirs")
    path = tmp_path / "out" / "capture"
    path.mkdir(parents=True)
    (path / "old.txt").write_text("the previous run's")
    pid = os.getpid()
    for kind in ("tmp", "old"):
        for name in [f".capture.{pid}.{kind}"] + [f".capture.{pid}.{t}.{kind}" for t in PLANTED_TOKENS]:
            (path.parent / name).symlink_to(outside, target_is_directory=True)
    with io.atomic_dir(path) as tmp:
        (tmp / "new.txt").write_text("this run's")
    assert sorted(p.name for p in outside.iterdir()) == ["keep.txt"] and (outside / "keep.txt").read_text() == "theirs"
    assert not path.is_symlink() and sorted(p.name for p in path.iterdir()) == ["new.txt"]


def test_a_link_planted_at_an_output_lock_is_not_written_through(tmp_path):
    """A stage's lock beside its output folder (pig._outputs.output_lock), truncated and written by its holder."""
    from pig._outputs import OutputError, output_lock

    outside = tmp_path / "precious.bin"
    outside.write_bytes(b"not to be touched")
    output = tmp_path / "out" / "fit"
    output.parent.mkdir()
    (output.parent / ".fit.lock").symlink_to(outside)
    with pytest.raises(OutputError):
        with output_lock(output, "fit"):
            pass
    assert outside.read_bytes() == b"not to be touched" and (output.parent / ".fit.lock").is_symlink()


def test_a_temporary_swapped_for_a_link_while_written_is_not_renamed_into_place(tmp_path):
    outside = tmp_path / "precious.bin"
    outside.write_bytes(b"not to be touched")
    path = tmp_path / "out" / "notes.txt"
    with pytest.raises(OSError):
        with io.atomic_path(path) as tmp:
            tmp.write_text("half")
            tmp.unlink()
            tmp.symlink_to(outside)
    assert not os.path.lexists(path) and outside.read_bytes() == b"not to be touched"
    assert list(path.parent.iterdir()) == []


def test_remove_orphans_finds_the_random_temporaries_of_dead_writers(tmp_path):
    child = subprocess.Popen(["true"])
    child.wait()
    dead = child.pid
    path = tmp_path / "avatar.pt"
    orphans = [f".avatar.{dead}.0a1b2c3d.tmp.pt", f".avatar.pt.{dead}.0a1b2c3d.tmp", f".avatar.pt.{dead}.ffffffff.old"]
    kept = [f".avatar.{os.getpid()}.0a1b2c3d.tmp.pt", f".avatar.{dead}.0a1b2c3.tmp.pt",
            f".avatar.{dead}.XYZ12345.tmp.pt"]
    for name in orphans + kept:
        (tmp_path / name).write_bytes(b"")
    mine = io._temporary(path)  # this process's own, alive: kept
    assert sorted(p.name for p in io.remove_orphans(path)) == sorted(orphans)
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(kept + [mine.name])
    # The writers' own names are of the form remove_orphans takes for a dead writer's.
    (tmp_path / mine.name.replace(f".{os.getpid()}.", f".{dead}.")).write_bytes(b"")
    assert [p.name for p in io.remove_orphans(path)] == [mine.name.replace(f".{os.getpid()}.", f".{dead}.")]

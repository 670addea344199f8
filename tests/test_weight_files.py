"""`pig weights`: the weight table, lookups and checksums, and the checksummed fetch against a local HTTP server
(good file, wrong checksum, 404, a transfer cut off, a trickle, links planted at the temporary's name), with the
table's URLs and hashes monkeypatched."""
from __future__ import annotations

import errno
import hashlib
import http.server
import itertools
import os
import re
import threading
from pathlib import Path

import pytest

import pig._io
import pig.metrics.weight_files as wf
from pig.metrics.weight_files import FetchError, WeightFile, check_and_fetch, fetch, status

GOOD = os.urandom(3 * wf.CHUNK + 123)  # several blocks of the reader
OTHER = os.urandom(5000)


TRICKLE_PIECE = 64


class _Handler(http.server.BaseHTTPRequestHandler):
    hits: list[str] = []

    def do_GET(self):
        _Handler.hits.append(self.path)
        if self.path in ("/good.pth", "/wrong.pth"):
            body = GOOD if self.path == "/good.pth" else OTHER
            self.send_response(200)
            self.send_header("Content-Length", str(len(body)))
            self.end_headers()
            self.wfile.write(body)
        elif self.path == "/endless.pth":  # no Content-Length, and far more than the published size
            self.send_response(200)
            self.end_headers()
            for _ in range(64):
                self.wfile.write(OTHER * 20)
            self.close_connection = True
        elif self.path == "/trickle.pth":  # the whole file, in small pieces, each flushed
            self.send_response(200)
            self.send_header("Content-Length", str(len(GOOD)))
            self.end_headers()
            sent = 0
            try:
                while sent < len(GOOD):
                    self.wfile.write(GOOD[sent : sent + TRICKLE_PIECE])
                    self.wfile.flush()
                    sent += TRICKLE_PIECE
            except (BrokenPipeError, ConnectionResetError):  # the client gave up
                pass
            self.close_connection = True
        elif self.path == "/cut.pth":  # promises the whole file, sends a third, then closes
            self.send_response(200)
            self.send_header("Content-Length", str(len(GOOD)))
            self.end_headers()
            self.wfile.write(GOOD[: len(GOOD) // 3])
            self.wfile.flush()
            self.close_connection = True
        else:
            self.send_error(404, "Not Found")

    def log_message(self, *args):
        pass


@pytest.fixture(scope="module")
def server():
    httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), _Handler)
    thread = threading.Thread(target=httpd.serve_forever, daemon=True)
    thread.start()
    yield f"http://127.0.0.1:{httpd.server_address[1]}"
    httpd.shutdown()
    httpd.server_close()


@pytest.fixture
def hub(tmp_path, monkeypatch):
    """An empty torch hub cache and no lpips package folder, and urllib without proxies (the server is local)."""
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "torch_home"))
    for name in ("http_proxy", "HTTP_PROXY", "https_proxy", "HTTPS_PROXY", "all_proxy", "ALL_PROXY"):
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setattr(wf, "lpips_package_weights", lambda: None)
    return tmp_path / "torch_home" / "hub" / "checkpoints"


def entry(server: str, path: str, content: bytes | None = GOOD, filename: str = "good.pth") -> WeightFile:
    digest = hashlib.sha256(content).hexdigest() if content is not None else None
    return WeightFile(path.strip("/").split(".")[0], filename, server + path, digest, len(GOOD), "test", "test")


def leftovers(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir()) if folder.exists() else []


def test_a_good_file_is_fetched_checked_and_listed_ok(server, hub):
    good = entry(server, "/good.pth")
    path = fetch(good, hub, report=lambda line: None)
    assert path == hub / "good.pth" and path.read_bytes() == GOOD
    assert leftovers(hub) == ["good.pth"]  # no temporary left beside it
    assert status(good).checksum == "ok" and status(good).ok


def test_a_wrong_checksum_is_deleted_and_reported(server, hub):
    wrong = entry(server, "/wrong.pth", content=GOOD, filename="wrong.pth")  # the server sends OTHER
    with pytest.raises(FetchError, match=f"SHA-256 of the download .* is {hashlib.sha256(OTHER).hexdigest()}"):
        fetch(wrong, hub, report=lambda line: None)
    assert leftovers(hub) == []


def test_a_404_is_reported_with_the_url(server, hub):
    with pytest.raises(FetchError, match=r"HTTP 404 .*/absent\.pth"):
        fetch(entry(server, "/absent.pth"), hub, report=lambda line: None)
    assert leftovers(hub) == []


def test_an_interrupted_transfer_keeps_nothing(server, hub):
    with pytest.raises(FetchError, match="cut off|failed after"):
        fetch(entry(server, "/cut.pth"), hub, report=lambda line: None)
    assert leftovers(hub) == []


def test_a_download_past_the_published_size_is_stopped(server, hub):
    # The server sends 6.4 MB with no length; the file is published at len(GOOD) bytes: stopped there, not at the end.
    with pytest.raises(FetchError, match=rf"sent more than the {len(GOOD):,} bytes of the published file; stopped"):
        fetch(entry(server, "/endless.pth"), hub, report=lambda line: None)
    assert leftovers(hub) == []


def test_a_trickling_server_is_given_up_on(server, hub):
    """Every block of the trickle takes 30 s by the injected clock: two blocks (at most 2 MiB) fall short of the
    3 MB that a minute at the 50 kB/s floor brings, so the fetch gives up before the file's end, keeping nothing."""
    ticks = itertools.count(0.0, 30.0)
    with pytest.raises(FetchError, match="too slow"):
        fetch(entry(server, "/trickle.pth"), hub, report=lambda line: None, clock=lambda: next(ticks))
    assert leftovers(hub) == []
    assert next(ticks) <= 4 * 30.0  # the clock was read at the start and after each of at most two blocks
    # The bound is of the transfer's rate, not its length: the same trickle, a microsecond a block, is fetched.
    steady = itertools.count(0.0, 1e-6)
    assert fetch(entry(server, "/trickle.pth"), hub, report=lambda line: None, clock=lambda: next(steady)).read_bytes() == GOOD


def test_links_planted_at_the_temporarys_names_are_not_written_through(server, hub, monkeypatch):
    """A link at the download's would-be temporary name (the earlier fixed one, or the first random ones) to a file
    outside the destination: that file is unchanged, and the fetched file is a file of its own."""
    outside = hub.parent / "precious.bin"
    hub.mkdir(parents=True)
    outside.write_bytes(b"not to be touched")
    planted = ["00000000", "00000001"]
    tokens = itertools.chain(planted, (f"{i:08x}" for i in itertools.count(0xB0000000)))
    monkeypatch.setattr(pig._io, "_token", lambda: next(tokens), raising=False)
    names = [f".good.{os.getpid()}.tmp.pth"] + [f".good.{os.getpid()}.{t}.tmp.pth" for t in planted]
    for name in names:
        (hub / name).symlink_to(outside)
    path = fetch(entry(server, "/good.pth"), hub, report=lambda line: None)
    assert outside.read_bytes() == b"not to be touched"
    assert not path.is_symlink() and not path.samefile(outside) and path.read_bytes() == GOOD
    assert leftovers(hub) == sorted(names + ["good.pth"])


def test_a_weight_of_the_wrong_size_is_bad_without_being_read(hub, monkeypatch):
    content = b"published bytes"
    table_entry = WeightFile("w", "w.pth", "http://unused/w.pth", hashlib.sha256(content).hexdigest(), len(content),
                             "test", "test")
    hashed = []
    monkeypatch.setattr(wf, "file_sha256", lambda path: hashed.append(path) or hashlib.sha256(path.read_bytes()).hexdigest())
    hub.mkdir(parents=True)
    (hub / "w.pth").write_bytes(content + b"and a long tail")
    assert status(table_entry).checksum == "bad" and hashed == []
    (hub / "w.pth").write_bytes(content.upper())  # the published size: hashed
    assert status(table_entry).checksum == "bad" and hashed == [hub / "w.pth"]
    (hub / "w.pth").write_bytes(content)
    assert status(table_entry).ok


def test_a_destination_that_is_a_file_or_not_writable_is_named(server, hub, tmp_path, monkeypatch, capsys):
    from pig.cli import main

    monkeypatch.setattr(wf, "WEIGHT_FILES", (entry(server, "/good.pth"),))
    dest = tmp_path / "a-file"
    dest.write_bytes(b"mine")
    assert main(["weights", "--fetch", "--dest", str(dest)]) == 1
    out = capsys.readouterr().out
    assert f"{dest}: is a file, not a folder" in out and out.count("not a folder") == 1
    assert main(["weights", "--fetch", "--dest", str(dest / "below")]) == 1
    assert f"lies under {dest}, which is a file" in capsys.readouterr().out
    assert dest.read_bytes() == b"mine"

    def refuse(path):
        raise PermissionError(errno.EACCES, "Permission denied", str(path))

    monkeypatch.setattr(wf, "create_temporary", refuse, raising=False)  # as a folder of another user does
    hits = len(_Handler.hits)
    with pytest.raises(FetchError) as refused:
        fetch(entry(server, "/good.pth"), tmp_path / "theirs", report=lambda line: None)
    assert "cannot write in its folder (Permission denied)" in str(refused.value)
    assert len(_Handler.hits) == hits  # refused before any download


def test_a_file_without_a_confirmed_checksum_is_refused_without_a_request(server, hub):
    unconfirmed = entry(server, "/good.pth", content=None)
    before = len(_Handler.hits)
    with pytest.raises(FetchError, match="no SHA-256 of it was confirmed"):
        fetch(unconfirmed, hub, report=lambda line: None)
    assert len(_Handler.hits) == before and leftovers(hub) == []


def test_fetch_replaces_nothing_that_was_there(server, hub, monkeypatch):
    """A corrupt file where the good one belongs is reported bad and left as it was; the missing one is fetched."""
    good, other = entry(server, "/good.pth"), entry(server, "/good.pth", filename="other.pth")
    monkeypatch.setattr(wf, "WEIGHT_FILES", (good, other))
    hub.mkdir(parents=True)
    (hub / "good.pth").write_bytes(b"corrupt")
    lines = []
    assert not check_and_fetch(fetch_missing=True, report=lines.append)
    assert (hub / "good.pth").read_bytes() == b"corrupt"
    assert (hub / "other.pth").read_bytes() == GOOD
    assert any("checksum bad" in line and "good.pth" in line for line in lines)
    assert re.search(r"^good\s+good\.pth\s+bad\b", "\n".join(lines), re.M)
    assert re.search(r"^good\s+other\.pth\s+ok\b", "\n".join(lines), re.M)


def test_dest_folder_and_only(server, hub, tmp_path, monkeypatch):
    good, absent = entry(server, "/good.pth"), entry(server, "/absent.pth", filename="absent.pth")
    monkeypatch.setattr(wf, "WEIGHT_FILES", (good, absent))
    dest = tmp_path / "mine"
    assert check_and_fetch(["good"], fetch_missing=True, dest=dest, report=lambda line: None)
    assert leftovers(dest) == ["good.pth"] and leftovers(hub) == []
    assert not check_and_fetch(["good", "absent"], fetch_missing=True, dest=dest, report=lambda line: None)
    with pytest.raises(ValueError, match="unknown weight file name"):
        check_and_fetch(["nope"])


def test_lookup_order_hub_then_lpips_package(hub, tmp_path, monkeypatch):
    package = tmp_path / "lpips" / "weights" / "v0.1"
    package.mkdir(parents=True)
    monkeypatch.setattr(wf, "lpips_package_weights", lambda: package)
    linear = next(f for f in wf.WEIGHT_FILES if f.name == "lpips-vgg")
    (package / "vgg.pth").write_bytes(b"not the published bytes")
    found = status(linear)
    assert found.path == package / "vgg.pth" and found.checksum == "bad" and not found.ok
    hub.mkdir(parents=True)
    (hub / "vgg.pth").write_bytes(b"x")
    assert status(linear).path == hub / "vgg.pth"  # the hub cache first, as pig.metrics.lpips looks
    assert status(linear, configured=tmp_path / "elsewhere.pth").searched == [tmp_path / "elsewhere.pth"]


@pytest.mark.parametrize("env", [{"TORCH_HOME": "/x/th"}, {"XDG_CACHE_HOME": "/x/xdg"}, {}])
def test_hub_folder_is_torchs(env, monkeypatch):
    import torch

    for name in ("TORCH_HOME", "XDG_CACHE_HOME"):
        monkeypatch.delenv(name, raising=False)
    for name, value in env.items():
        monkeypatch.setenv(name, value)
    assert wf.hub_checkpoints() == Path(torch.hub.get_dir()) / "checkpoints"


def test_the_table_names_the_published_files():
    for f in wf.WEIGHT_FILES:
        assert f.url.endswith("/" + f.filename)
        assert f.sha256 is not None and re.fullmatch(r"[0-9a-f]{64}", f.sha256)
        prefix = re.search(r"-([0-9a-f]{8})\.pth$", f.filename)  # torchvision's names carry the first 8 hex digits
        if prefix:
            assert f.sha256.startswith(prefix.group(1))


def test_pig_weights_lists_and_fetches(server, hub, monkeypatch, capsys):
    from pig.cli import main

    monkeypatch.setattr(wf, "WEIGHT_FILES", (entry(server, "/good.pth"),))
    assert main(["weights"]) == 1
    out = capsys.readouterr().out
    assert re.search(r"^good\s+good\.pth\s+missing\b", out, re.M) and "pig weights --fetch" in out
    assert main(["weights", "--fetch"]) == 0
    assert re.search(r"^good\s+good\.pth\s+ok\b.*" + re.escape(str(hub / "good.pth")), capsys.readouterr().out, re.M)


def test_loss_defaults_are_the_fits(hub, monkeypatch):
    """The torch-free reading of a preset's `fit` section sees FitConfig's defaults, and names what the term lacks."""
    from dataclasses import fields

    from pig.avatar.fit_config import FitConfig

    defaults = {f.name: f.default for f in fields(FitConfig)}
    assert wf.LOSS_DEFAULTS == {key: defaults[key] for key in wf.LOSS_DEFAULTS}
    assert [line.split(":")[0] for line in wf.loss_weight_problems({})] == ["vgg16", "lpips-vgg"]
    assert wf.loss_weight_problems({"weight_lpips": 0.0}) == []
    assert wf.loss_weight_problems({"lpips_weights": "random"}) == []
    content = b"stand-in"
    table = [WeightFile(f.name, f.filename, f.url, hashlib.sha256(content).hexdigest(), 8, "test", "test",
                        f.in_lpips_package) for f in wf.WEIGHT_FILES]
    monkeypatch.setattr(wf, "WEIGHT_FILES", tuple(table))
    hub.mkdir(parents=True)
    (hub / "alexnet-owt-7be5be79.pth").write_bytes(content)
    (hub / "alex.pth").write_bytes(b"other")
    assert [line.split(":")[0] for line in wf.loss_weight_problems({"lpips_net": "alex"})] == ["lpips-alex"]
    assert "checksum bad" in wf.loss_weight_problems({"lpips_net": "alex"})[0]
    # The user's own weights, configured by path, are loaded as they are: not refused for their checksum, only absent.
    own = {"lpips_net": "alex", "lpips_linear_weights": str(hub / "alex.pth")}
    assert wf.loss_weight_problems(own) == []
    missing = {"lpips_net": "alex", "lpips_linear_weights": str(hub / "absent.pth")}
    assert [line.split(":")[0] for line in wf.loss_weight_problems(missing)] == ["lpips-alex"]

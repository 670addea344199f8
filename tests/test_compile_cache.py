"""benchmarks/fit_gpu.py --compile-cache: torch.compile's artifacts written gzipped and loaded back (a later round of
fits in a GPU hold skips most of its compilation)."""
import sys
from pathlib import Path

import pytest
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from fit_gpu import load_compile_cache, save_compile_cache  # noqa: E402


def test_missing_file_loads_nothing(tmp_path):
    assert load_compile_cache(tmp_path / "absent.bin.gz") is False


@pytest.mark.filterwarnings("ignore")
def test_what_was_compiled_comes_back(tmp_path):
    torch._dynamo.reset()
    compiled = torch.compile(lambda x: torch.sin(x) * 3 + x.square(), backend="inductor", dynamic=False)
    x = torch.randn(257)
    torch.testing.assert_close(compiled(x), torch.sin(x) * 3 + x.square())
    path = tmp_path / "pig.bin.gz"
    save_compile_cache(path)
    assert path.is_file() and not (tmp_path / "pig.bin.gz.partial").exists()
    info = torch.compiler.load_cache_artifacts(__import__("gzip").decompress(path.read_bytes()))
    assert info is not None and len(info.inductor_artifacts) >= 1  # the graph just compiled, not an empty cache
    assert load_compile_cache(path) is True

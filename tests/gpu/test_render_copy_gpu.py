"""The render stage's uint8 conversion on the GPU: a camera group's views come back through page-locked memory
equal to the CPU's conversion of the same colours, and stay intact while later groups reuse freed host blocks.

Run on the GPU machine (skipped without CUDA)."""
import numpy as np
import pytest
import torch

from pig.stages.render import _to_u8

pytestmark = [
    pytest.mark.gpu,
    pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA"),
]


def test_group_copy_through_pinned_memory_matches_the_cpu_conversion():
    generator = torch.Generator().manual_seed(0)
    colours = [torch.rand((4, 37, 53, 3), generator=generator) * 1.2 - 0.1 for _ in range(4)]
    expected = [_to_u8(colour) for colour in colours]  # the CPU path: no pinned memory
    kept = [_to_u8(colour.cuda()) for colour in colours[:2]]  # whole groups held
    views = [_to_u8(colour.cuda())[1] for colour in colours[2:]]  # one view each: its group's array is gone
    for _ in range(8):  # later groups, each freed at once: their host blocks go back to the cache and are reused
        _to_u8(torch.rand((4, 37, 53, 3), device="cuda"))
    for got, want in zip(kept, expected[:2]):
        assert got.dtype == np.uint8 and got.shape == want.shape
        np.testing.assert_array_equal(got, want)
    for view, want in zip(views, expected[2:]):
        np.testing.assert_array_equal(view, want[1])

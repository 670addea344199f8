"""npz reading of body parameters and body models: anything that is not an npz archive is one clear error naming
the file (never advice to allow pickles), and loading never runs code stored in the file."""
from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp
import torch

from pig.body.model import NUM_JOINTS, SMPLX_PARENTS, BodyModel, BodyModelError
from pig.body.params import ParamsError, SmplxParams


def _object(value) -> np.ndarray:
    holder = np.empty((), dtype=object)
    holder[()] = value
    return holder


class _RunsCode:
    """Unpickling this calls open(path, "w"): a file appears if the loader ran code from the archive."""

    def __init__(self, path):
        self.path = str(path)

    def __reduce__(self):
        return open, (self.path, "w")


def _small_model_arrays(rng, num_vertices=30) -> dict[str, np.ndarray]:
    regressor = rng.random((NUM_JOINTS, num_vertices)) * (rng.random((NUM_JOINTS, num_vertices)) < 0.2)
    regressor[:, 0] += 1e-3  # no empty row
    return {
        "v_template": rng.normal(size=(num_vertices, 3)), "f": rng.integers(0, num_vertices, size=(20, 3)),
        "shapedirs": rng.normal(size=(num_vertices, 3, 20)), "posedirs": rng.normal(size=(num_vertices, 3, 486)),
        "J_regressor": regressor / regressor.sum(axis=1, keepdims=True),
        "weights": rng.dirichlet(np.ones(NUM_JOINTS), size=num_vertices),
        "kintree_table": np.stack([SMPLX_PARENTS, np.arange(NUM_JOINTS)]),
    }


def _smplx_npz(path):
    n = 3
    np.savez(path, poses=np.zeros((n, 165)), betas=np.zeros((1, 10)), expression=np.zeros((n, 10)),
             transl=np.zeros((n, 3)), frames=np.arange(n))
    return path


NOT_NPZ = {
    "random bytes": (lambda p: p.write_bytes(np.random.default_rng(0).bytes(2048)), r"the file starts with b'"),
    "empty": (lambda p: p.write_bytes(b""), r"the file is empty"),
    "an .npy file": (lambda p: p.write_bytes(b"\x93NUMPY" + bytes(100)), r"the file starts with b'\\x93NUM'"),
    "a pickle": (lambda p: p.write_bytes(b"\x80\x04\x95\x05\x00\x00\x00\x00\x00\x00\x00K\x01."),
                 r"starts with b'\\x80"),
    "truncated": (lambda p: p.write_bytes(_smplx_npz(p).read_bytes()[:700]), r"truncated or corrupt"),
}


@pytest.mark.parametrize("case", sorted(NOT_NPZ))
@pytest.mark.parametrize("load, error", [(SmplxParams.load, ParamsError), (BodyModel.from_file, BodyModelError)])
def test_not_an_npz_archive_is_one_line_naming_the_file(tmp_path, case, load, error):
    path = tmp_path / "weights.npz"
    write, detail = NOT_NPZ[case]
    write(path)
    with pytest.raises(error, match=rf"weights\.npz: not a valid npz archive \(.*{detail}") as raised:
        load(path)
    message = str(raised.value)
    assert "pickle" not in message and "\n" not in message and "expected" in message


def test_pickled_objects_in_parameters_are_refused_without_running_them(tmp_path):
    marker = tmp_path / "ran"
    path = _smplx_npz(tmp_path / "smplx.npz")
    arrays = dict(np.load(path))
    np.savez(path, **{**arrays, "transl": _object(_RunsCode(marker))})
    with pytest.raises(ParamsError, match=r"smplx\.npz: 'transl' holds pickled Python objects, which are not loaded"):
        SmplxParams.load(path)
    assert not marker.exists()


def test_body_model_with_a_sparse_pickled_regressor_loads_and_code_is_never_run(tmp_path):
    arrays = _small_model_arrays(np.random.default_rng(0))
    dense = BodyModel(arrays, dtype=torch.float64)
    extra = {"joint2num": _object({"pelvis": 0}), "vt": np.zeros((4, 2))}  # keys the model does not use
    sparse_path = tmp_path / "sparse.npz"
    np.savez(sparse_path, **{**arrays, **extra, "J_regressor": _object(sp.csc_matrix(arrays["J_regressor"]))})
    loaded = BodyModel.from_file(sparse_path, dtype=torch.float64)
    np.testing.assert_array_equal(loaded.j_regressor.numpy(), dense.j_regressor.numpy())
    np.testing.assert_array_equal(loaded.posedirs.numpy(), dense.posedirs.numpy())

    marker = tmp_path / "ran"
    for key in ("J_regressor", "joint2num"):  # a key the model reads, and one it skips
        path = tmp_path / f"crafted_{key}.npz"
        np.savez(path, **{**arrays, key: _object(_RunsCode(marker))})
        if key == "J_regressor":
            with pytest.raises(BodyModelError, match=r"'J_regressor' holds pickled objects other than numpy arrays or "
                                                     r"scipy sparse matrices \(refused to load \w+\.open\)"):
                BodyModel.from_file(path)
        else:
            BodyModel.from_file(path)
        assert not marker.exists()


def test_headers_are_parsed_one_thread_at_a_time(tmp_path, monkeypatch):
    # CPython 3.11's AST construction keeps its depth per interpreter: two threads parsing .npy headers at once can
    # fail (python/cpython#106905). Each parse here sleeps, so threads that were not kept apart would overlap.
    import ast
    import threading
    import time

    from pig.body.npz import read_npz

    paths = []
    for i in range(4):
        paths.append(tmp_path / f"a{i}.npz")
        np.savez(paths[-1], x=np.arange(6.0).reshape(2, 3) + i, y=np.ones(2))
    literal_eval, inside, most = ast.literal_eval, [0], [0]
    guard = threading.Lock()

    def slow_literal_eval(text):
        with guard:
            inside[0] += 1
            most[0] = max(most[0], inside[0])
        time.sleep(0.01)
        try:
            return literal_eval(text)
        finally:
            with guard:
                inside[0] -= 1

    monkeypatch.setattr(ast, "literal_eval", slow_literal_eval)
    results = [None] * len(paths)

    def read(i):
        results[i] = read_npz(paths[i], ValueError, "a test archive")

    threads = [threading.Thread(target=read, args=(i,)) for i in range(len(paths))]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert most[0] == 1  # never two parses at once
    for i, arrays in enumerate(results):  # and every archive read whole
        np.testing.assert_array_equal(arrays["x"], np.arange(6.0).reshape(2, 3) + i)
        np.testing.assert_array_equal(arrays["y"], np.ones(2))

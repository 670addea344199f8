"""A tiny body model for tests that need the SMPL-X layout, not a body."""
import numpy as np
import trimesh

from pig.body.model import SMPLX_PARENTS


def tiny_body_model(rng):
    """An SMPL-X-layout body model on an icosphere (162 vertices): for tests that need the layout, not a body."""
    sphere = trimesh.creation.icosphere(subdivisions=2)
    count = len(sphere.vertices)
    weights = rng.random((count, 55)) ** 4
    regressor = rng.random((55, count))
    return dict(v_template=np.asarray(sphere.vertices), f=np.asarray(sphere.faces),
                J_regressor=regressor / regressor.sum(1, keepdims=True), weights=weights / weights.sum(1, keepdims=True),
                shapedirs=rng.normal(scale=0.01, size=(count, 3, 20)), posedirs=rng.normal(scale=0.01, size=(count, 3, 486)),
                kintree_table=np.stack([SMPLX_PARENTS, np.arange(55)]))

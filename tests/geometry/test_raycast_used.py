"""The vertices a caster's faces use (``prtlab.geometry._raycast._used_vertices``), which set its bounds."""

import numpy as np

from prtlab.geometry import RayCaster
from prtlab.geometry._raycast import _used_vertices


def test_used_vertices_are_numpys_unique(rng):
    """The mask gives ``np.unique(faces)``, values and dtype: unused vertices, repeated ones, no faces."""
    for n_vertices, n_faces in [(1, 1), (10, 3), (500, 40), (50, 400), (7, 0)]:
        faces = rng.integers(0, n_vertices, size=(n_faces, 3))
        ours, numpys = _used_vertices(faces, n_vertices), np.unique(faces)
        assert ours.dtype == numpys.dtype and np.array_equal(ours, numpys)


def test_unused_vertices_do_not_set_the_bounds():
    """A far vertex no face uses leaves the caster's box and offset as without it."""
    v = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [50.0, 50.0, 50.0]])
    f = np.array([[0, 1, 2]])
    caster, alone = RayCaster([(v, f)]), RayCaster([(v[:3], f)])
    assert np.array_equal(caster.bounds, alone.bounds) and caster.epsilon == alone.epsilon
    assert np.array_equal(caster.bounds, [[0.0, 0.0, 0.0], [1.0, 1.0, 0.0]])

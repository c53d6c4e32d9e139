import numpy as np
import pytest

from prtlab.portals import find_portals, frosted, shell_light, shell_sh, tint

from .conftest import window_box


def test_find_portals_window(constant_box):
    (portal,) = find_portals(constant_box)
    assert portal.names == ("window",)
    np.testing.assert_allclose(portal.center, [0, 1.4, -1.5], atol=1e-12)
    np.testing.assert_allclose(portal.normal, [0, 0, 1], atol=1e-12)  # into the room
    assert portal.area == pytest.approx(1.0)
    assert portal.size == pytest.approx(np.sqrt(2.0))


def test_find_portals_groups_errors(constant_box):
    with pytest.raises(ValueError, match="exactly once"):
        find_portals(constant_box, groups=[["window"], ["window"]])
    with pytest.raises(TypeError, match="list of lists"):
        find_portals(constant_box, groups="window")
    with pytest.raises(TypeError, match="prtlab.Scene"):
        find_portals(None)


def test_shell_light_constant_and_sh():
    cube = shell_light(np.array([1.0, 2.0, 3.0]), 8)
    assert cube.shape == (6, 8, 8, 3)
    c = shell_sh(cube, 3)
    np.testing.assert_allclose(c[0], np.sqrt(4 * np.pi) * np.array([1, 2, 3]), rtol=1e-10)
    np.testing.assert_allclose(c[1:], 0, atol=1e-10)


def test_shell_light_sources(sky_box):
    env = sky_box.environment
    a = shell_light(env, 8)
    b = shell_light(env.image, 8)
    np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(shell_light(a, 8), a)
    with pytest.raises(ValueError, match=r"\(6, 16, 16, 3\)"):
        shell_light(a, 16)
    with pytest.raises(ValueError, match="power of two"):
        shell_light(a, 6)
    with pytest.raises(ValueError, match="NaN"):
        shell_light(np.array([np.nan, 1, 1]), 8)
    with pytest.raises(ValueError, match="equirect"):
        shell_light(np.ones((4, 4)), 8)
    with pytest.raises(ValueError, match=r"\(6, r, r, 3\)"):
        shell_sh(np.ones((6, 4, 4)), 2)


def test_tint_and_frosted(sky_box):
    cube = shell_light(sky_box.environment, 8)
    np.testing.assert_allclose(tint(cube, [0.5, 0.5, 1.0])[..., 2], cube[..., 2])
    flat = shell_light(np.array([1.0, 1.0, 1.0]), 8)
    np.testing.assert_allclose(frosted(flat, 10.0), flat, rtol=1e-12)  # a blur keeps a constant
    blurred = frosted(cube, 20.0)
    from prtlab.geometry import cubemap_solid_angles

    w = cubemap_solid_angles(8)[..., None]
    assert blurred.max() < cube.max()
    np.testing.assert_allclose((blurred * w).sum(), (cube * w).sum(), rtol=0.05)  # energy roughly kept
    with pytest.raises(ValueError, match="colour"):
        tint(cube, [1, -1, 0])
    with pytest.raises(ValueError, match="sigma_deg"):
        frosted(cube, 0.0)
    with pytest.raises(ValueError, match=r"\(6, r, r, 3\)"):
        frosted(np.ones(3), 1.0)


def test_portal_without_area():
    from prtlab.portals._shell import _make_portal

    with pytest.raises(ValueError, match="has no area"):
        _make_portal(("flat",), [(np.zeros((3, 3)), np.array([[0, 1, 2]]))])


def test_shell_sh_against_reference_quadrature(sky_box):
    import prtlab.sh as sh
    from prtlab.geometry import cubemap_directions, cubemap_solid_angles

    cube = shell_light(sky_box.environment, 8)
    dirs = cubemap_directions(8).reshape(-1, 3)
    w = cubemap_solid_angles(8).reshape(-1)
    expected = sh.basis_reference(dirs, 4).T @ (w[:, None] * cube.reshape(-1, 3))
    np.testing.assert_allclose(shell_sh(cube, 4), expected, rtol=1e-10, atol=1e-12)
    with pytest.raises(ValueError, match="order must be an int"):
        shell_sh(cube, 0)


def test_shell_light_tiers(sky_box, rng):
    """The tap-table kernel reproduces equirect_to_cubemap (the reference tier) for any image size."""
    env = sky_box.environment
    for res in (4, 8):
        np.testing.assert_allclose(shell_light(env, res), shell_light(env, res, method="reference"),
                                   rtol=1e-12, atol=1e-14)
    for shape in ((9, 20, 3), (32, 64, 3), (16, 200, 3)):
        img = rng.random(shape)
        np.testing.assert_allclose(shell_light(img, 8), shell_light(img, 8, method="reference"), rtol=1e-12)
    with pytest.raises(ValueError, match="'numba' or 'reference'"):
        shell_light(env, 8, method="gpu")

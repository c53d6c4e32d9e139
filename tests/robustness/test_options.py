"""Every option of every pipeline refuses bad values, with a message naming the option.

The cases are generated from ``dataclasses.fields`` of each options dataclass and the type of the
field's default, so an option added without validation fails here. Wrong types are a TypeError, right
types out of range a ValueError (docs/DECISIONS.md, "Bad input").
"""

from __future__ import annotations

import dataclasses
import math

import pytest

from prtlab.interreflection import InterreflectionOptions
from prtlab.portals import PortalsOptions
from prtlab.spherelights import SphereLightOptions

OPTIONS = {"portals": PortalsOptions, "spherelights": SphereLightOptions, "interreflection": InterreflectionOptions}

#: fields whose default does not tell their type: (bad value, error) cases of their own
SPECIAL = {
    "n_spheres": [(2.7, TypeError), ("many", TypeError), (0, ValueError), ({"ball": 2.5}, TypeError),
                  ({"ball": 0}, ValueError), ({3: 2}, TypeError)],
    "local_lights": [(5, TypeError), ([((0, 1, 0), -0.3, (1, 1, 1))], ValueError),
                     ([((0, 1, 0), 0.3, (1, 1, math.nan))], ValueError)],
    "degree": [(15.0, TypeError), ("47", TypeError), (-1, ValueError)],
}


def _bad_values(default):
    """(value, error) cases that every option with this default's type must refuse."""
    if isinstance(default, bool):
        return [(1, TypeError), ("yes", TypeError)]
    if isinstance(default, int):
        return [(2.7, TypeError), (2.0, TypeError), ("many", TypeError), (True, TypeError), (-1, ValueError)]
    if isinstance(default, float):
        return [("0.5", TypeError), (True, TypeError), (math.nan, ValueError), (math.inf, ValueError),
                (-1.0, ValueError)]
    if isinstance(default, str):
        return [("banana", ValueError), (3, ValueError)]
    return None


def _cases():
    for method, options in OPTIONS.items():
        for f in dataclasses.fields(options):
            default = f.default if f.default is not dataclasses.MISSING else f.default_factory()
            cases = SPECIAL.get(f.name) or _bad_values(default)
            if cases is None:
                yield pytest.param(method, f.name, None, None, id=f"{method}-{f.name}-unknown")
                continue
            for value, error in cases:
                yield pytest.param(method, f.name, value, error, id=f"{method}-{f.name}-{value!r}")


@pytest.mark.parametrize("method, name, value, error", list(_cases()))
def test_every_option_refuses_a_bad_value_naming_the_option(method, name, value, error):
    assert error is not None, f"option {name} of {method}: no bad values known for its type; add them to SPECIAL"
    with pytest.raises(error, match=rf"\boption {name}\b"):
        OPTIONS[method](**{name: value})


@pytest.mark.parametrize("method", list(OPTIONS))
def test_the_defaults_are_valid(method):
    OPTIONS[method]()


@pytest.mark.parametrize("method, options, error, message", [
    ("interreflection", {"r_min": 3.0, "r_max": 2.0}, ValueError,
     r"options r_min and r_max must satisfy r_min <= r_max, got r_min=3.0 > r_max=2.0"),
    ("interreflection", {"irradiance": "haar"}, ValueError, r"option irradiance='haar' needs .* shadows='haar'"),
    ("interreflection", {"cube_resolution": 12}, ValueError, r"option cube_resolution must be a power of two"),
    ("interreflection", {"spacing": "banana"}, ValueError,
     r"option spacing must be one of 'geometric', 'uniform', got 'banana'"),
    ("portals", {"cube_resolution": 12}, ValueError, r"option cube_resolution must be a power of two"),
    ("spherelights", {"n_directions": 50}, ValueError, r"option n_directions must be the vertex count 10 f\^2 \+ 2"),
    ("spherelights", {"n_directions": 0}, ValueError, r"option n_directions must be an int >= 12"),
    ("spherelights", {"hierarchy_children": 1}, ValueError, r"option hierarchy_children must be 0 .* or an int >= 2"),
    ("spherelights", {"cut_threshold": 1.0}, ValueError, r"option cut_threshold must be a finite number >= 0.0 and "
                                                          r"< 1.0"),
    ("spherelights", {"n_spheres": 2.7}, TypeError, r"option n_spheres must be an int >= 1 .*got 2.7 of type float"),
])
def test_cross_field_and_special_limits(method, options, error, message):
    with pytest.raises(error, match=message):
        OPTIONS[method](**options)


def test_good_values_of_each_kind_are_accepted():
    SphereLightOptions(n_spheres={"ball": 3}, n_directions=42, cut_threshold=0,
                       local_lights=[((0, 1, 0), 0.2, (1, 1, 1))])
    InterreflectionOptions(r_min=0.5, r_max=0.5, spacing="uniform", degree=15, threshold=1, near_field=0)
    PortalsOptions(merge_portals=True, direct_basis="haar", glossy_order=0, bounces=0)

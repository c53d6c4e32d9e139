"""Guerrero et al. 2008 spherical-lights pipeline (issue 6).

Not implemented yet: this subpackage is reserved by ../shared/DESIGN.md.
"""

__all__: list[str] = []

"""Yue et al. 2009 portals pipeline (issue 7).

Not implemented yet: this subpackage is reserved by ../shared/DESIGN.md.
"""

__all__: list[str] = []

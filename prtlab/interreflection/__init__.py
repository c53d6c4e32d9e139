"""Iwasaki et al. 2007 interreflection pipeline (issue 5).

Not implemented yet: this subpackage is reserved by ../shared/DESIGN.md.
"""

__all__: list[str] = []

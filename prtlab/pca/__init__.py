"""PCA basis functions and the basis comparison of the Iwasaki journal paper (issue 4).

Not implemented yet: this subpackage is reserved by ../shared/DESIGN.md.
"""

__all__: list[str] = []

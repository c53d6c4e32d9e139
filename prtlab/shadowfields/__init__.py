"""Zhou et al. 2005 shadow fields (issue 5).

Not implemented yet: this subpackage is reserved by ../shared/DESIGN.md.
"""

__all__: list[str] = []

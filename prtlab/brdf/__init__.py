"""Lambert and Phong BRDFs and their separable approximation (issue 4).

Not implemented yet: this subpackage is reserved by ../shared/DESIGN.md.
"""

__all__: list[str] = []

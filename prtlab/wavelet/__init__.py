"""2D Haar wavelets on cubemaps, triple products, pulse basis and 8-bit quantisation (issue 4).

Not implemented yet: this subpackage is reserved by ../shared/DESIGN.md.
"""

__all__: list[str] = []

"""docs/OPTIONS.md is generated from the options dataclasses and is current."""

import dataclasses
from pathlib import Path

import pytest

from prtlab.api import PIPELINES, option_docs, options_reference, pipeline_class

ROOT = Path(__file__).resolve().parents[1]


def test_the_options_reference_is_current():
    text = (ROOT / "docs" / "OPTIONS.md").read_text()
    assert text == options_reference(), "docs/OPTIONS.md is stale: python -m prtlab.api --options-doc > docs/OPTIONS.md"


@pytest.mark.parametrize("method", sorted(PIPELINES))
def test_every_option_of_every_pipeline_has_a_row_with_its_default(method):
    options_type = pipeline_class(method).options_type
    docs = option_docs(options_type)
    reference = options_reference()
    for f in dataclasses.fields(options_type):
        kind, doc = docs[f.name]
        assert kind and doc, f.name
        default = f.default if f.default is not dataclasses.MISSING else f.default_factory()
        assert f"| `{f.name}` | " in reference and f"`{default!r}`" in reference


def test_grouped_entries_document_each_name():
    @dataclasses.dataclass
    class Opts:
        """Toy.

        Attributes
        ----------
        a, b : int
            Both ``a`` and
            ``b``.
        c : {"x", "y"}
            One | two.

        Notes
        -----
        d : not an option
        """

    assert option_docs(Opts) == {"a": ("int", "Both ``a`` and ``b``."), "b": ("int", "Both ``a`` and ``b``."),
                                 "c": ('{"x", "y"}', "One | two.")}


def test_an_undocumented_option_is_an_error(monkeypatch):
    from prtlab.portals import PortalsOptions

    doc = PortalsOptions.__doc__.replace("    seed : int\n", "    seedling : int\n")
    monkeypatch.setattr(PortalsOptions, "__doc__", doc)
    with pytest.raises(ValueError, match=r"option 'seed' of PortalsOptions has no entry in its docstring's Attributes "
                                         r"section; document it there"):
        options_reference()

"""A Griffe extension for the API pages: the docstrings use Sphinx roles
(``:class:`~inject.errors.InputError```, ``:func:`mask_image```), which Markdown would show
as they are typed; this turns each into a code span of the name (the last part after ``~``,
the title of ``title <target>``)."""
import re

import griffe

ROLE = re.compile(r":(?:py:)?(?:class|func|meth|mod|data|attr|obj|exc|const|ref|term):"
                  r"`(?P<text>[^`]+)`")


def _name(match):
    text = match.group("text").strip()
    titled = re.fullmatch(r"(?P<title>.*\S)\s*<[^>]+>", text)
    if titled:
        return f"`{titled.group('title')}`"
    if text.startswith("~"):
        text = text[1:].rsplit(".", 1)[-1]
    return f"`{text}`"


class SphinxRoles(griffe.Extension):
    """Rewrite Sphinx cross-reference roles in every docstring as code spans."""

    def on_instance(self, *, obj, **kwargs):
        if obj.docstring is not None:
            obj.docstring.value = ROLE.sub(_name, obj.docstring.value)

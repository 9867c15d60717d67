"""mkdocs hook (mkdocs.yml `hooks:`): the docstrings' reStructuredText roles, such as
:class:`~humotion.sparse.recording.HeadsetStream`, shown as plain code in the API reference
(mkdocstrings renders docstrings as Markdown, which leaves the role and the tilde in the text)."""

import re

ROLE = re.compile(r":(?:class|meth|func|mod|attr|data|exc|obj):(<code>)~?")


def on_page_content(html, **_):
    return ROLE.sub(r"\1", html)

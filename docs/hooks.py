"""MkDocs hook: render the Sphinx roles in srvwire's docstrings as code, linked where possible.

The docstrings name other objects the Sphinx way (``:class:`~srvwire.errors.RPCError```). The
API reference renders them as Markdown, which would show the role literally. This hook turns
each role into inline code showing the name as Sphinx would (the last part after ``~``), and
asks mkdocs-autorefs to link it when the object has a page; an object without one (a private
helper, the standard library) stays plain code, without a warning.
"""

from __future__ import annotations

import html
import re
from typing import Any

ROLE = re.compile(r":(?:class|func|meth|attr|mod|exc|data|obj):<code>(~?)([\w.]+)</code>")


def _replace(match: re.Match[str]) -> str:
    short, path = match.groups()
    shown = path.rsplit(".", 1)[-1] if short else path
    return (
        f'<autoref identifier="{html.escape(path)}" optional>'
        f"<code>{html.escape(shown)}</code></autoref>"
    )


def on_page_content(html_text: str, /, **kwargs: Any) -> str:
    """Replace every role that the Markdown renderer left in the page."""
    return ROLE.sub(_replace, html_text)

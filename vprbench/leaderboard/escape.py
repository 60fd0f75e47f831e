"""Text from data on pages: the one escape every page writer uses."""
from __future__ import annotations

import html


def text(value) -> str:
    """Text from data or records (names, labels, paths, reasons) as plain text in Markdown: no
    HTML element, no link or image, no table cell break can come from it."""
    out = html.escape(str(value), quote=True).replace("|", "\\|").replace("](", "]\\(")
    return out.replace("\n", " ")

"""Text that runs recorded, made safe for the markdown tables and lines of every report: one escaping
function, so a name, an override or an error message never becomes markup, a link, a heading or a
second table row."""

from __future__ import annotations


def md_cell(text: object) -> str:
    """Text from a run as one markdown table cell, list item or part of a line: no HTML tag or entity
    ('&', '<' escaped), no link ('[' escaped), no '|', '`' or line break (so no heading either)."""
    flat = " ".join(str(text).split())
    return (
        flat.replace("&", "&amp;")
        .replace("<", "&lt;")
        .replace("[", "&#91;")
        .replace("|", "&#124;")
        .replace("`", "&#96;")
    )

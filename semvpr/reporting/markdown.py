"""Text that runs recorded, made safe for the markdown tables and lines of every report: one escaping
function, so a name, an override or an error message never becomes markup, a link, a heading or a
second table row."""

from __future__ import annotations

import html
from collections.abc import Iterable


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


def terminal_text(lines: Iterable[str]) -> str:
    """Lines of a report's markdown as a terminal shows them: the entities :func:`md_cell` wrote read back as
    the characters they stand for (``&#91;`` is ``[``), any control character of the recorded text dropped, so
    nothing a run recorded moves the cursor or changes the terminal's state."""
    text = "\n".join(html.unescape(line) for line in lines)
    return "".join(c for c in text if c == "\n" or c.isprintable())

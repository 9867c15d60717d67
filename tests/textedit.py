"""Editing helpers for the malformed-file tests."""


def replace_line(text: str, line: int, new: str | None) -> str:
    """Replace (or delete, new=None) 1-based line `line` of text."""
    lines = text.split("\n")
    if new is None:
        del lines[line - 1]
    else:
        lines[line - 1] = new
    return "\n".join(lines)

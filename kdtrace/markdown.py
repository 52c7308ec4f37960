"""The one writer of compact GitHub Markdown tables (cells as given, no padding).

Used wherever a page writes a table of cells it has already formatted (and, for text from
outside, escaped): the quality table of ``kdtrace quality``, the scale-out page and the
verdict page. The tables of the other report parts are laid out by ``tabulate``.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence


def markdown_table(headers: Sequence[str], rows: Iterable[Sequence[str]],
                   right_aligned: Sequence[bool] | None = None) -> str:
    """A GitHub Markdown table: a header line, an alignment line, a line per row.

    Parameters
    ----------
    headers : sequence of str
        Column headers, as they should appear.
    rows : iterable of sequences of str
        The cells of each row, already formatted (and escaped where they need it).
    right_aligned : sequence of bool, optional
        Per column, whether it is right-aligned (``---:``); default every column left (``---``).

    Returns
    -------
    str
        The table's lines, each ending in a newline.
    """
    aligned = right_aligned if right_aligned is not None else [False] * len(headers)
    lines = ["| " + " | ".join(headers) + " |", "|" + "".join("---:|" if right else "---|" for right in aligned)]
    lines += ["| " + " | ".join(row) + " |" for row in rows]
    return "\n".join(lines) + "\n"

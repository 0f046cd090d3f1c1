"""
Markdown tables, as the docs, the reproductions and the demo print them (pure Python).

One writer for every table the package prints: the parameter tables of
docs/nodes.md (:func:`bcid_ros.parameter_spec.markdown_table`), the
reproductions' tables in docs/reproduction_*.md, the benchmark summary and
the demo's final table.
"""

from __future__ import annotations

from typing import Iterable, Sequence


def markdown_table(headers: Sequence[str], rows: Iterable[Sequence[object]]) -> str:
    """
    Return a GitHub Markdown table, a newline at its end.

    Parameters
    ----------
    headers : sequence of str
        The column titles.
    rows : iterable of sequence
        The cells, each printed with ``str`` (format floats first).

    """
    lines = ['| ' + ' | '.join(headers) + ' |', '|' + '---|' * len(headers)]
    lines.extend('| ' + ' | '.join(str(cell) for cell in row) + ' |' for row in rows)
    return '\n'.join(lines) + '\n'


__all__ = ['markdown_table']

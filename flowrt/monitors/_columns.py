"""Tables that fit the terminal: columns dropped by rank, names never cut.

The live status table, the recording's per-stream table and ``flowrt info`` are read in
80-column terminals as often as in wide ones. A table too wide for its terminal makes rich
squeeze every column, and the names (the one thing a reader scans for) come out as
``fron…``. So each column carries a drop rank: at a narrow width the columns are dropped in
rank order (1 first) until the table fits; rank 0 is never dropped.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Generic, TypeVar

from rich import box
from rich.cells import cell_len
from rich.table import Table
from rich.text import Text

__all__ = ["Cell", "Column", "fit_table"]

S = TypeVar("S")  # a row
Cell = str | Text


@dataclass(frozen=True)
class Column(Generic[S]):
    header: str
    cell: Callable[[S], Cell]
    drop: int = 0  # 0: essential; else dropped in ascending order when space is short
    right: bool = True


def fit_table(
    cols: Sequence[Column[S]],
    rows: Sequence[S],
    width: int | None,
    title: str | None = None,
    row_style: Callable[[S], str | None] | None = None,
) -> Table:
    """The rows under the widest set of columns that fits ``width`` (dropping by rank).

    Widths are computed here rather than measured by rich (which renders every cell once per
    try: ~40 ms for the cambada table at 80 columns, against ~4 ms for this).
    """
    cells: dict[str, list[Cell]] = {}
    natural: dict[str, int] = {}
    for col in cols:
        cells[col.header] = [col.cell(r) for r in rows]
        widths = [cell_len(x.plain if isinstance(x, Text) else x) for x in cells[col.header]]
        natural[col.header] = max([cell_len(col.header), *widths])
    ranks: list[int] = sorted({c.drop for c in cols if c.drop})
    shown = list(cols)
    for limit in [0, *ranks]:  # drop the columns ranked up to ``limit``
        shown = [c for c in cols if not c.drop or c.drop > limit]
        # each column: one space of padding on its right (none after the last), then the
        # box's blank divider
        if width is None or sum(natural[c.header] + 2 for c in shown) - 2 <= width:
            break
    table = Table(
        title=title,
        title_justify="left",
        box=box.SIMPLE_HEAD,
        show_edge=False,
        pad_edge=False,
        padding=(0, 1, 0, 0),
        expand=False,
    )
    for c in shown:
        table.add_column(
            c.header,
            justify="right" if c.right else "left",
            no_wrap=True,
            min_width=None if c.right else natural[c.header],  # names are never cut first
        )
    for i, row in enumerate(rows):
        style = row_style(row) if row_style is not None else None
        table.add_row(*(cells[c.header][i] for c in shown), style=style)
    return table

"""What every report shares: its markdown tables and the style of its figures.

The experiments of the paper (`hrp2_drake.paper`) and the any-robot commands
(`hrp2_drake.tools`) write their reports with these, so that a table or a figure
looks the same wherever it comes from. This module imports nothing from the package.

    markdown_table(["joint", "error (mrad)"], [["knee", "1.25"]])
    -> ["| joint | error (mrad) |", "| --- | ---: |", "| knee | 1.25 |"]

Figures: `pyplot()` draws off screen, `legend_beside(ax)` puts a legend beside its
axes (off the data), `save_figure(fig, path)` writes it at the reports' resolution
and closes it.
"""

from collections.abc import Iterable, Sequence
from pathlib import Path

#: The alignment row's marker of each letter of `markdown_table`'s `align`.
ALIGNMENTS = {"l": "---", "r": "---:", "c": ":---:"}

#: The reports' figure resolution (dots per inch); the tools' logs plots use 100.
FIGURE_DPI = 110

#: A legend beside its axes, its top left corner at the axes' top right corner.
LEGEND_BESIDE = {"loc": "upper left", "bbox_to_anchor": (1.01, 1.0), "borderaxespad": 0}


def markdown_table(
    header: Sequence[str],
    rows: Iterable[Sequence[str | None]],
    align: str | None = None,
) -> list[str]:
    """A markdown table as lines: the header, the alignment row, one line per row.

    Each cell is written between "| " and " |" as given (already formatted): "" is
    an empty cell written with its two spaces ("|  |"); None is an empty cell written
    with one ("| |").

    Args:
        header: the column titles.
        rows: each row's cells, one per column.
        align: one letter per column: "l" left ("---"), "r" right ("---:"), "c"
            centred (":---:"). Default: the first column left, the others right.

    Raises:
        ValueError: `align` of another length than the header or with another letter,
            or a row with another number of cells than the header.
    """
    if align is None:
        align = "l" + "r" * (len(header) - 1)
    if len(align) != len(header) or not set(align) <= set(ALIGNMENTS):
        raise ValueError(
            f"markdown_table: align '{align}' must have one of the letters "
            f"{'/'.join(ALIGNMENTS)} per column of the header ({len(header)})"
        )
    lines = [_row(header), _row([ALIGNMENTS[a] for a in align])]
    for k, row in enumerate(rows):
        if len(row) != len(header):
            raise ValueError(
                f"markdown_table: row {k} has {len(row)} cells, the header "
                f"{len(header)} ({list(header)})"
            )
        lines.append(_row(row))
    return lines


def _row(cells: Sequence[str | None]) -> str:
    """One line of a table: "| a | b |"; a None cell as "| |"."""
    return "|" + "".join(" |" if cell is None else f" {cell} |" for cell in cells)


def pyplot():
    """matplotlib.pyplot, drawing off screen (the Agg backend): what every report's
    plotting function starts with."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def legend_beside(ax, fontsize: float = 8, **kwargs):
    """`ax.legend` beside the axes, off the data (`LEGEND_BESIDE`); `kwargs` are
    passed on (and may override its placement)."""
    return ax.legend(fontsize=fontsize, **(LEGEND_BESIDE | kwargs))


def save_figure(
    fig, path: str | Path, dpi: float = FIGURE_DPI, tight: bool = False
) -> None:
    """Writes `fig` to `path` at `dpi` (laid out by `fig.tight_layout()` first with
    `tight`) and closes it."""
    if tight:
        fig.tight_layout()
    fig.savefig(path, dpi=dpi)
    pyplot().close(fig)

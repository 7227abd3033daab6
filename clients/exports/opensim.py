"""The table layout OpenSim's files share (``.mot``, ``.sto``); its names and
frames are in ``core/opensim.py``."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from bodynet.core.opensim import OPENSIM_FROM_BODYNET

#: Rows: OpenSim's X, Y, Z axes in bodynet's frame (``core.opensim``).
TO_OPENSIM = np.array(OPENSIM_FROM_BODYNET)


def header(lines: Sequence[str], columns: Sequence[str]) -> str:
    """An OpenSim table file's header: its lines (``key=value``...), then
    ``endheader`` and the tab-separated column labels."""
    return "\n".join([*lines, "endheader", "\t".join(columns)]) + "\n"


def format_rows(time_s: np.ndarray, cells: Sequence[Sequence[str]]) -> str:
    """Tab-separated rows: the time (s), then each row's cells."""
    return "".join(
        f"{t:.6f}\t" + "\t".join(row) + "\n" for t, row in zip(time_s.tolist(), cells, strict=True)
    )


def number(value: float) -> str:
    """A cell: NaN as ``nan`` (read as NaN by OpenSim's readers)."""
    return f"{value + 0.0:.8g}"  # + 0.0: -0 as 0

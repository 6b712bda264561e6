"""Faults the simulated cell injects (`cell_sim_node`'s `faults`, `hrc-case-study --faults`).

An entry is ``KIND:EPOCHS`` with EPOCHS one epoch ``7`` or a range ``7-9`` (epochs count from
1; the cell is in epoch k after k - 1 reactions):

- ``dropout``: no joint states and no skeletons during those epochs (a sensor dropout);
- ``nan_velocity``: joint states whose velocities are NaN during those epochs;
- ``decline``: the human declines every request made in those epochs;
- ``collision``: the human steps into the collision circle as those epochs begin (d = 0).
"""

from __future__ import annotations

from typing import Iterable

FAULT_KINDS = ('dropout', 'nan_velocity', 'decline', 'collision')


def parse_faults(entries: Iterable[str]) -> dict[str, list[tuple[int, int]]]:
    """``["dropout:5", "collision:7-8"]`` -> {kind: [(first, last) epoch ranges]};
    ValueError naming the entry if one is malformed."""
    faults: dict[str, list[tuple[int, int]]] = {kind: [] for kind in FAULT_KINDS}
    for entry in entries:
        kind, sep, span = str(entry).partition(':')
        first, dash, last = span.partition('-')
        if kind not in faults or not sep:
            raise ValueError(f'fault {entry!r}: expected KIND:EPOCHS with KIND one of '
                             f'{", ".join(FAULT_KINDS)}')
        try:
            low, high = int(first), int(last if dash else first)
        except ValueError:
            raise ValueError(f'fault {entry!r}: EPOCHS must be "k" or "k-m"') from None
        if not 1 <= low <= high:
            raise ValueError(f'fault {entry!r}: epochs must satisfy 1 <= k <= m')
        faults[kind].append((low, high))
    return faults


def active(faults: dict[str, list[tuple[int, int]]], kind: str, epoch: int) -> bool:
    """Whether fault `kind` is injected in `epoch`."""
    return any(low <= epoch <= high for low, high in faults[kind])

"""Antenna layouts of TI's evaluation boards: TX and RX positions (azimuth, elevation) in half wavelengths, from which
a configuration's virtual array follows (virtual element = TX position + RX position).

- ``xwr1843boost`` (AWR1843BOOST, IWR1843BOOST): RX0..RX3 on a line at 0, 1, 2, 3; TX0 at 0 and TX2 at 4 on the same
  row; TX1 one row up (elevation 1) at azimuth 2, so that its four virtual elements sit above azimuth 2..5. Source:
  OpenRadar's ``mmwave/dsp/angle_estimation.py`` (the "TI xWR1843 virtual antenna map" of
  ``beamforming_naive_mixed_xyz`` and the azimuth offset of 2 in ``naive_xyz``), which follows TI's board user guide.
- ``xwr1642boost`` (AWR1642BOOST, IWR1642BOOST): RX0..RX3 at 0..3, TX0 at 0 and TX1 at 4 (two wavelengths apart): a
  uniform line of 8 virtual elements (TI's xWR16xx mmWave SDK demo processes them as one 8-element line).

Other boards (IWR6843AOP, cascade boards, ...) are not listed: state their positions in the profile's ``[array]``.
"""

from __future__ import annotations

from radar.ti.cfg import TiConfigError

Position = tuple[float, float]
BOARDS: dict[str, tuple[tuple[Position, ...], tuple[Position, ...]]] = {
    # name: (TX positions by TX number, RX positions by RX number)
    "xwr1843boost": (((0, 0), (2, 1), (4, 0)), ((0, 0), (1, 0), (2, 0), (3, 0))),
    "xwr1642boost": (((0, 0), (4, 0)), ((0, 0), (1, 0), (2, 0), (3, 0))),
}


def board_name(name: str) -> str:
    """The table's key of a board name: case-insensitive, AWR/IWR/xWR alike."""
    key = name.lower()
    if key[:3] in ("awr", "iwr"):
        key = "xwr" + key[3:]
    if key not in BOARDS:
        raise TiConfigError(f"unknown board {name!r}; known: {sorted(BOARDS)}, each also spelled with awr or iwr for "
                            f"xwr (or state the positions in the profile's [array] virtual_azimuth / "
                            f"virtual_elevation)")
    return key


def virtual_positions(board: str, tx_numbers: tuple[int, ...], rx_numbers: tuple[int, ...]) -> list[Position]:
    """(azimuth, elevation) of each virtual element ``k = t * n_rx + r``, ``t`` indexing ``tx_numbers`` and ``r``
    ``rx_numbers``, on ``board``."""
    tx_table, rx_table = BOARDS[board_name(board)]
    for what, numbers, table in (("TX", tx_numbers, tx_table), ("RX", rx_numbers, rx_table)):
        missing = [n for n in numbers if n >= len(table)]
        if missing:
            raise TiConfigError(f"board {board}: has no {what} {missing} ({len(table)} {what})")
    return [(tx_table[t][0] + rx_table[r][0], tx_table[t][1] + rx_table[r][1])
            for t in tx_numbers for r in rx_numbers]

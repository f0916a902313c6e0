"""A plain CSV format, so any logger's data can be replayed without writing a reader.

Format (one header row of column names, then one row per IMU sample)::

    # world: NED          optional, NED (default) or ENU: the frame of the reference
    # reference: truth    optional, truth (default) or autopilot
    # north: true         optional, true (default) or magnetic: the reference's north
    t,gx,gy,gz,ax,ay,az,mx,my,mz,qw,qx,qy,qz,score
    0.000,0.01,-0.02,0.00,0.1,0.2,-9.80,0.21,0.02,0.43,1,0,0,0,1

* ``t`` seconds (any origin, increasing; duplicates / backwards rows are dropped and counted)
* ``gx gy gz`` rad/s and ``ax ay az`` m/s² (specific force: about [0, 0, -9.81] level in
  FRD/NED), body axes FRD unless the reference uses other body axes consistently
* ``mx my mz`` optional magnetometer, any unit
* ``qw qx qy qz`` optional reference attitude [w, x, y, z], body -> world, on the same
  rows; empty or NaN where unknown
* ``score`` optional 0/1: which rows count for the RMSE (default all)
* a row with a cell that is not a number (``abc``, ``1.2.3``) or with more or fewer cells
  than the header (a file cut mid-row) is dropped; the recording's notes say how many
  and the first one's line

Lines starting with ``#`` are comments, apart from the ``key: value`` settings above.
"""

from __future__ import annotations

import io
import warnings
from collections.abc import Callable
from pathlib import Path

import numpy as np

from ..board import magnitude_warning
from ..dataset import NORTH_KINDS, REFERENCE_KINDS, Recording, ReplayInputError
from ._common import clean_stream, make_reference, pick_reference

IMU_COLUMNS = ("t", "gx", "gy", "gz", "ax", "ay", "az")
MAG_COLUMNS = ("mx", "my", "mz")
REF_COLUMNS = ("qw", "qx", "qy", "qz")


def read(path: Path, reference: str = "auto") -> Recording:
    settings, header, body_start = _preamble(path)
    _refuse_duplicate_columns(path, header)
    missing = [c for c in IMU_COLUMNS if c not in header]
    if missing:
        raise ReplayInputError(f"{path}: no IMU samples found (CSV lacks columns {missing}; "
                               f"expected {','.join(IMU_COLUMNS)}[,mx,my,mz][,qw,qx,qy,qz]"
                               f"[,score])")
    table, lines, ragged = _read_table(path, body_start, len(header))
    table, damage = _drop_non_numeric_rows(
        table, lambda: lines if lines is not None else _data_lines(path, body_start))
    table, spikes = _drop_time_spikes(table, header.index("t"))
    notes = tuple(n for n in (_dropped_note(ragged, "with a wrong number of cells"), damage,
                              spikes) if n)

    def cols(names: tuple[str, ...]) -> np.ndarray | None:
        if not all(n in header for n in names):
            return None
        return table[:, [header.index(n) for n in names]]

    world = settings.get("world", "NED").upper()
    kind = settings.get("reference", "truth").lower()
    north = settings.get("north", "true").lower()
    if world not in ("NED", "ENU") or kind not in REFERENCE_KINDS or north not in NORTH_KINDS:
        raise ReplayInputError(f"{path}: world must be NED/ENU, reference one of "
                               f"{REFERENCE_KINDS} and north one of {NORTH_KINDS}, got "
                               f"{world!r}, {kind!r}, {north!r}")
    t_raw = table[:, header.index("t")]
    extra = [c for c in (cols(MAG_COLUMNS), cols(REF_COLUMNS), cols(("score",))) if c is not None]
    t, (gyr, acc, *rest), cleanup = clean_stream(
        t_raw, cols(("gx", "gy", "gz")), cols(("ax", "ay", "az")), *extra)
    if len(t) < 2:
        raise ReplayInputError(f"{path}: fewer than 2 IMU rows with increasing time"
                               + "".join(f"; {n}" for n in notes))
    mag = rest.pop(0) if "mx" in header and all(c in header for c in MAG_COLUMNS) else None
    q = rest.pop(0) if all(c in header for c in REF_COLUMNS) else None
    score = rest.pop(0)[:, 0] > 0.5 if "score" in header else None
    found = None if q is None else make_reference(t, q, kind, "csv qw,qx,qy,qz", north=north)
    ref, references = pick_reference({kind: found}, reference)
    warning = magnitude_warning(acc, "the CSV's ax,ay,az")
    return Recording(path=path, format="csv", t=t, gyr=gyr, acc=acc, mag=mag, world=world,
                     body="FRD", source="csv", reference=ref, score_mask=score,
                     cleanup=cleanup, notes=notes, damage=notes,  # (each says a loss)
                     warnings=(warning,) if warning else (), references=references)


def _read_table(path: Path, body_start: int, columns: int
                ) -> tuple[np.ndarray, list[tuple[int, list[str]]] | None, list[int]]:
    """The data rows as floats, the rows as text when they had to be read so, and the
    line numbers of rows dropped for another number of cells than the header's.

    A row with more or fewer cells (a file cut mid-row, two lines run together) cannot
    be paired with the columns: it is dropped and counted, like a row with a cell that
    is no number. genfromtxt refuses the whole file for one, so only then is the file
    read line by line (slower) and the rows that fit handed to it.
    """
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # "Empty input file": said below in our words
        try:
            table = np.genfromtxt(path, delimiter=",", skip_header=body_start,
                                  comments="#", dtype=float, ndmin=2,
                                  filling_values=np.nan)
            if table.size and table.shape[1] == columns:
                return table, None, []
        except ValueError:
            pass
    lines = _data_lines(path, body_start)
    if not lines:
        raise ReplayInputError(f"{path}: no data rows after the header")
    ragged = [number for number, cells in lines if len(cells) != columns]
    lines = [(number, cells) for number, cells in lines if len(cells) == columns]
    if not lines:
        raise ReplayInputError(f"{path}: rows must have {columns} values like the header")
    text = io.StringIO("\n".join(",".join(cells) for _, cells in lines))
    table = np.genfromtxt(text, delimiter=",", dtype=float, ndmin=2, filling_values=np.nan)
    return table, lines, ragged


def _drop_non_numeric_rows(table: np.ndarray,
                           rows_as_text: Callable[[], list[tuple[int, list[str]]]]
                           ) -> tuple[np.ndarray, str]:
    """The table without rows that have a cell that is no number, and a note saying how
    many and where the first is ("" when none); ``rows_as_text`` gives the table's rows
    as (line number, cells), called only when a row holds a NaN.

    genfromtxt reads such a cell ("1.2.3", "abc", a line garbled by a crash) as NaN,
    like an empty cell or a written "nan", which mean "unknown" in this format. Only the
    rows that hold a NaN are looked at again as text, to tell the two apart.
    """
    suspects = np.flatnonzero(np.isnan(table).any(axis=1))
    if not suspects.size:
        return table, ""
    lines = rows_as_text()
    bad = [k for k in suspects.tolist() if not all(map(_number_or_empty, lines[k][1]))]
    return (np.delete(table, bad, axis=0),
            _dropped_note([lines[k][0] for k in bad], "with non-numeric cells"))


def _refuse_duplicate_columns(path: Path, header: list[str]) -> None:
    """One column per name: with two ``gx`` columns only the first would be read, and
    which of the two holds the gyro is a guess."""
    first: dict[str, int] = {}
    for number, name in enumerate(header, start=1):
        if name and name in first:
            raise ReplayInputError(f"{path}: duplicate column {name} in the header "
                                   f"(columns {first[name]} and {number}); each name once")
        first[name] = number


def _drop_time_spikes(table: np.ndarray, column: int) -> tuple[np.ndarray, str]:
    """The table without rows whose time is a lone spike, and a note saying how many.

    A spike is a row later than the next two rows while the row before it and the next
    row are in order: one corrupt stamp (1e9 among seconds). Left in, it is the running
    maximum and every row after it would be dropped as going backwards. A clock that
    really goes back (a reset) stays behind the row before the jump, so it is no spike and
    the rows after it are dropped and counted as before; a row merely swapped with the
    next one only hides that one row and is left to that count too.

    The last row has no next row to be out of line with; it is a spike when its one step
    is longer than the whole recording before it (a stamp that alone would more than
    double the recording, with nothing after it to show a clock that moved on).
    """
    t = table[:, column]
    if t.shape[0] < 3:
        return table, ""
    before = np.concatenate(([-np.inf], t[:-2]))  # row k-1 for rows 0..n-2
    after, after2 = t[1:], np.concatenate((t[2:], [np.inf]))
    spike = np.flatnonzero((t[:-1] > after) & (t[:-1] > after2) & (before < after))
    kept = np.delete(t, spike)  # the last row is never among those: it has no next row
    if kept.shape[0] >= 3 and kept[-1] - kept[-2] > kept[-2] - kept[0] > 0.0:
        spike = np.append(spike, t.shape[0] - 1)
    if not spike.size:
        return table, ""
    rows = "row" if spike.size == 1 else "rows"
    first = spike[0]
    beside = (f"the next row's {t[first + 1]:g} s" if first + 1 < t.shape[0]
              else f"the row before's {t[first - 1]:g} s")
    return (np.delete(table, spike, axis=0),
            f"CSV: {spike.size} {rows} with a time stamp out of line with the rows either "
            f"side dropped (first: t = {t[first]:g} s, {beside})")


def _dropped_note(line_numbers: list[int], why: str) -> str:
    """"CSV: N rows <why> dropped (first at line L)", or "" for none."""
    if not line_numbers:
        return ""
    rows = "row" if len(line_numbers) == 1 else "rows"
    return f"CSV: {len(line_numbers)} {rows} {why} dropped (first at line {line_numbers[0]})"


def _data_lines(path: Path, body_start: int) -> list[tuple[int, list[str]]]:
    """(line number, cells) of each data row, skipping what genfromtxt skips: the lines
    up to the header, comments (from ``#`` on) and blank lines."""
    out = []
    with path.open("r", encoding="utf-8-sig", errors="replace") as f:
        for number, line in enumerate(f, start=1):
            text = line.split("#", 1)[0].strip()
            if number > body_start and text:
                out.append((number, text.split(",")))
    return out


def _number_or_empty(cell: str) -> bool:
    text = cell.strip()
    if not text:
        return True
    try:
        float(text)
    except ValueError:
        return False
    return True


def _preamble(path: Path) -> tuple[dict[str, str], list[str], int]:
    """``# key: value`` settings, the header's column names, and the header's line count."""
    settings: dict[str, str] = {}
    with path.open("r", encoding="utf-8-sig", errors="replace") as f:  # Excel writes a BOM
        for number, line in enumerate(f):
            text = line.strip()
            if not text:
                continue
            if text.startswith("#"):
                key, sep, value = text[1:].partition(":")
                if sep:
                    settings[key.strip().lower()] = value.strip()
                continue
            return settings, [c.strip().lower() for c in text.split(",")], number + 1
    raise ReplayInputError(f"{path}: empty CSV (no header row)")


def write(path: Path, t: np.ndarray, gyr: np.ndarray, acc: np.ndarray,
          mag: np.ndarray | None = None, q_ref: np.ndarray | None = None,
          world: str = "NED", reference: str = "truth") -> None:
    """Write arrays in this format (used to export emulator runs and in tests)."""
    names = list(IMU_COLUMNS)
    parts = [np.asarray(t, float)[:, None], gyr, acc]
    if mag is not None:
        names += MAG_COLUMNS
        parts.append(mag)
    if q_ref is not None:
        names += REF_COLUMNS
        parts.append(q_ref)
    with Path(path).open("w", encoding="utf-8") as f:
        f.write(f"# world: {world}\n# reference: {reference}\n{','.join(names)}\n")
        np.savetxt(f, np.hstack(parts), delimiter=",", fmt="%.9g")

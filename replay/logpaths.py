"""What ``replay PATH...`` and ``tune PATH...`` mean by PATH: files, folders and globs.

* a file: that file, whatever its name (the readers also recognise a log by its first
  bytes);
* a folder: every file inside it, recursively, whose name ends in a suffix a reader
  knows (``.ulg``, ``.ulog``, ``.tlog``, ``.npz``, ``.csv``); hidden files and folders
  (``.git``, ``.cache``) are skipped and symbolic links to folders are not followed, so
  a link loop cannot make the list endless;
* a pattern (``'logs/**/*.tlog'``, quoted so that the shell leaves it alone): what it
  matches (``**`` crosses folders), a matched folder as above;
* anything else (a missing file): kept, so that it is reported as the reader reports it
  ("no such file") beside the other logs.

The result is sorted by path and without duplicates: the order of the corpus summary
does not depend on the order of the arguments, the shell or the file system.
"""

from __future__ import annotations

import glob
import os
from collections.abc import Iterable, Sequence
from pathlib import Path

from .dataset import ReplayInputError
from .readers import LOG_SUFFIXES

#: Path("") is the current folder: an unset shell variable ($LOGS) would replay or tune
#: on everything below it.
EMPTY_PATH = "empty path (an unset shell variable?): give a log file, a folder or a pattern"


def log_path(text: str) -> Path:
    """A PATH argument as a Path; ReplayInputError for an empty one (see EMPTY_PATH)."""
    if not text:
        raise ReplayInputError(EMPTY_PATH)
    return Path(text)


def is_pattern(text: str) -> bool:
    return glob.has_magic(text)


def is_corpus(paths: Sequence[str | Path]) -> bool:
    """More than one PATH, or one that stands for several (a folder, a pattern that is
    not the name of an existing file): the corpus replay. One file keeps the single-file
    replay (its figures, its time series, its exact output)."""
    if len(paths) != 1:
        return True
    p = Path(paths[0])
    return p.is_dir() or (not p.exists() and is_pattern(str(paths[0])))


def logs_in_folder(folder: Path) -> list[Path]:
    """Every readable-looking log under ``folder`` (see module docstring)."""
    found = []
    for root, dirs, files in os.walk(folder):  # followlinks=False: no link loops
        dirs[:] = [d for d in dirs if not d.startswith(".")]
        found += [Path(root, f) for f in files
                  if not f.startswith(".") and Path(f).suffix.lower() in LOG_SUFFIXES]
    return found


def expand(paths: Iterable[str | Path]) -> list[Path]:
    """The logs the PATH arguments stand for, sorted by path, each once.

    A folder without any log, a pattern that matches nothing or an empty path is an
    error (a typo should not shrink a corpus silently, nor an unset variable widen it).
    """
    out: list[Path] = []
    for arg in paths:
        p = log_path(os.fspath(arg))
        if p.is_dir():
            found = logs_in_folder(p)
            if not found:
                raise ReplayInputError(f"{p}: no logs in this folder (looked for "
                                       f"{', '.join(sorted(LOG_SUFFIXES))}, recursively)")
            out += found
        elif p.exists():
            out.append(p)
        elif not is_pattern(str(arg)):
            # as a pattern that matches nothing: a typo must not shrink the corpus
            raise ReplayInputError(f"{arg}: no such file or folder")
        else:
            matches = sorted(glob.glob(str(arg), recursive=True))
            if not matches:
                raise ReplayInputError(f"{arg}: no file matches this pattern")
            for m in map(Path, matches):
                out += logs_in_folder(m) if m.is_dir() else [m]
    seen: set[str] = set()
    unique = []
    for p in sorted(out, key=str):
        key = os.path.normcase(os.path.abspath(p))
        if key not in seen:
            seen.add(key)
            unique.append(p)
    return unique

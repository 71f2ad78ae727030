"""Reading and writing JSON documents with errors that name the file."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

from calib.errors import InputError


def read_json(path: str | Path, what: str = "file") -> Any:
    """Parse a JSON file; :class:`InputError` names the file and the line of a syntax error.

    Parameters
    ----------
    path : str or Path
        The file, UTF-8.
    what : str, optional
        What the file is, for the not-found message ("plan file", "dataset", ...).

    Returns
    -------
    Any
        The parsed document (dict, list, str, number, bool or None).

    Raises
    ------
    InputError
        If the file is missing or unreadable, is not valid JSON, or nests too deeply.
    """
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise InputError(f"{what} not found", file=str(p)) from None
    except OSError as exc:
        raise InputError(f"cannot read: {exc.strerror}", file=str(p)) from None
    try:
        return json.loads(text)
    except json.JSONDecodeError as exc:
        raise InputError(f"not valid JSON: {exc.msg} at line {exc.lineno} column {exc.colno}", file=str(p)) from None
    except RecursionError:
        raise InputError("JSON nested too deeply (arrays and objects within each other)", file=str(p)) from None


def fsync_dir(path: str | Path) -> None:
    """Flush a directory's entries to disk (after a rename in it: without this, a power cut can lose the rename
    although the file's data were synced). A no-op where directories cannot be opened (Windows).

    Parameters
    ----------
    path : str or Path
        The directory.
    """
    try:
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
    except (PermissionError, IsADirectoryError):  # pragma: no cover (Windows)
        return
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def write_json_atomic(path: str | Path, data: Any, indent: int | None = 1) -> None:
    """Write JSON to a temporary file, flush it, rename it over ``path`` and flush the directory: after a crash or a
    power cut, ``path`` holds the old or the new document, whole.

    Parameters
    ----------
    path : str or Path
        The destination file; its temporary sibling is ``.<name>.tmp`` in the same directory.
    data : Any
        A JSON-serialisable document.
    indent : int or None, optional
        ``json.dump``'s indent (1 by default; None for one line).
    """
    p = Path(path)
    tmp = p.with_name(f".{p.name}.tmp")
    with open(tmp, "w", encoding="utf-8") as fh:
        json.dump(data, fh, indent=indent)
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, p)
    fsync_dir(p.parent)

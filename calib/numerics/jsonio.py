"""Reading and writing JSON documents with errors that name the file; large documents written readable and fast
(:func:`dumps_readable`)."""

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


#: :func:`dumps_readable` lays out this many levels of nesting, one member a line; deeper values take one line each
READABLE_DEPTH = 3


def dumps_readable(data: Any, depth: int = READABLE_DEPTH) -> str:
    """JSON text of ``data``, its outer ``depth`` levels laid out one member a line (indented by one space a level),
    each value below on one line: readable and diffable, and written by the json module's C encoder.

    ``json.dumps(data, indent=1)`` runs the json module's pure-Python encoder (an indent disables the C one): a few
    times slower on an observations file. The text parses to the same value as ``json.dumps(data, indent=1)``'s (the
    same numbers, each float's shortest round-trip form; keys in the same order).

    Parameters
    ----------
    data : Any
        A JSON-serialisable document (dicts, lists or tuples, str, numbers, bool, None).
    depth : int, optional
        The levels laid out (0: one line). For an observations document, 3: its top level, its list of frames, each
        frame's members (a frame's board, legs, truth take a line each).

    Returns
    -------
    str
        The JSON text, no trailing newline.

    Raises
    ------
    TypeError
        A value that is not JSON-serialisable (as ``json.dumps``).
    """
    encode = json.JSONEncoder(check_circular=False).encode  # no indent: the C encoder

    def key(k: Any) -> str:
        # json's key conversion (numbers, bool, None as strings) by json itself: '{"5": 0}'[1:-4] is '"5"'
        return encode(k) if isinstance(k, str) else encode({k: 0})[1:-4]

    def walk(v: Any, level: int, pad: str) -> str:
        if level >= depth or not isinstance(v, dict | list | tuple) or not v:
            return encode(v)
        inner = pad + " "
        if isinstance(v, dict):
            lines = [f"{inner}{key(k)}: {walk(x, level + 1, inner)}" for k, x in v.items()]
            return "{\n" + ",\n".join(lines) + "\n" + pad + "}"
        return "[\n" + ",\n".join(inner + walk(x, level + 1, inner) for x in v) + "\n" + pad + "]"

    return walk(data, 0, "")


def write_json_atomic(path: str | Path, data: Any, indent: int | None = 1, readable: bool = False) -> None:
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
    readable : bool, optional
        Written by :func:`dumps_readable` instead (``indent`` unused): for large documents.
    """
    p = Path(path)
    tmp = p.with_name(f".{p.name}.tmp")
    with open(tmp, "w", encoding="utf-8") as fh:
        if readable:
            fh.write(dumps_readable(data))
        else:
            json.dump(data, fh, indent=indent)
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, p)
    fsync_dir(p.parent)

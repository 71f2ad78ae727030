"""Every public function of ``calib`` carries a numpydoc docstring, and no docstring tells a case history.

Rules checked, file by file:

- a public function (a module-level ``def`` whose name does not start with ``_``) and a public method of a public
  class that takes arguments besides ``self``/``cls`` has a docstring with a ``Parameters`` section naming each
  argument, and a ``Returns`` (or ``Yields``) section unless it returns ``None``;
- no docstring (module, class or function, nested ones included) contains a date (``YYYY-MM-DD``), an issue number
  (``issue 12``, ``#12``) or a commit id (7 to 40 hex digits, letters and digits mixed).

``PENDING`` lists the files whose docstrings are being rewritten elsewhere; they are skipped until it is emptied.
Run as a script (``python tests/calib/test_docstrings.py``) to print, per file, the count of public functions that
lack a section.
"""

from __future__ import annotations

import ast
import re
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest

import calib

CALIB = Path(calib.__file__).resolve().parent

#: Files (relative to ``calib/``, POSIX separators; a trailing ``/`` names a whole folder) skipped for now.
PENDING: frozenset[str] = frozenset()

_SECTION = re.compile(r"^\s*(Parameters|Returns|Yields|Raises|Other Parameters)\s*\n\s*-{3,}\s*$", re.MULTILINE)
_DATE = re.compile(r"\b(19|20)\d\d-[01]\d-[0-3]\d\b")
_ISSUE = re.compile(r"\b(issue|issues|PR|pull request)\s*#?\s*\d+\b|(?<![\w&])#\d+\b", re.IGNORECASE)
_HEX = re.compile(r"\b[0-9a-f]{7,40}\b")


def _is_commit_id(word: str) -> bool:
    return any(c.isdigit() for c in word) and any(c in "abcdef" for c in word)


def calib_files() -> list[Path]:
    """The ``.py`` files of ``calib`` not in ``PENDING``, sorted."""
    out = []
    for path in sorted(CALIB.rglob("*.py")):
        rel = path.relative_to(CALIB).as_posix()
        if rel in PENDING or any(p.endswith("/") and rel.startswith(p) for p in PENDING):
            continue
        out.append(path)
    return out


@dataclass(frozen=True)
class Finding:
    """One missing section or one forbidden word, at ``where`` (``file:line name``)."""

    where: str
    what: str


def _arg_names(fn: ast.FunctionDef | ast.AsyncFunctionDef, method: bool) -> list[str]:
    a = fn.args
    names = [x.arg for x in a.posonlyargs + a.args + a.kwonlyargs]
    if method and names and names[0] in ("self", "cls"):
        names = names[1:]
    if a.vararg:
        names.append("*" + a.vararg.arg)
    if a.kwarg:
        names.append("**" + a.kwarg.arg)
    return names


def _returns_value(fn: ast.FunctionDef | ast.AsyncFunctionDef) -> tuple[bool, bool]:
    """(returns a value, is a generator), from the annotation if there is one, else from the body."""
    own: list[ast.AST] = []
    stack: list[ast.AST] = list(fn.body)
    while stack:  # the function's own nodes, not those of nested functions, lambdas or classes
        node = stack.pop()
        own.append(node)
        for child in ast.iter_child_nodes(node):
            if not isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda, ast.ClassDef)):
                stack.append(child)
    gen = any(isinstance(n, (ast.Yield, ast.YieldFrom)) for n in own)
    if fn.returns is not None:
        text = ast.unparse(fn.returns).strip("'\"").replace(" ", "")
        if text in ("None", "NoReturn", "Never", "typing.NoReturn"):
            return False, gen
        if gen and re.fullmatch(r"(\w+\.)*(Async)?(Iterator|Generator)\[None(,.*)?\]", text):
            return False, gen  # a context manager's or a generator's bare ``yield``
        return True, gen
    return gen or any(isinstance(n, ast.Return) and n.value is not None for n in own), gen


def _section(doc: str, name: str) -> str | None:
    """The text of section ``name`` of a numpydoc docstring, or None if absent."""
    heads = list(_SECTION.finditer(doc))
    for i, m in enumerate(heads):
        if m.group(1) == name:
            end = heads[i + 1].start() if i + 1 < len(heads) else len(doc)
            return doc[m.end() : end]
    return None


def _documented_names(params: str) -> set[str]:
    names: set[str] = set()
    for line in params.splitlines():
        if line.strip() and not line.startswith((" ", "\t")):
            head = line.split(" : ")[0] if " : " in line else line
            names.update(n.strip() for n in head.split(","))
    return names


def _is_overload(fn: ast.FunctionDef | ast.AsyncFunctionDef) -> bool:
    return any(ast.unparse(d).split(".")[-1] == "overload" for d in fn.decorator_list)


def _check_function(fn: ast.FunctionDef | ast.AsyncFunctionDef, where: str, method: bool) -> list[Finding]:
    if _is_overload(fn):
        return []
    names = _arg_names(fn, method)
    if method and not names:
        return []
    doc = ast.get_docstring(fn)
    if doc is None:
        return [Finding(where, "no docstring")]
    doc = doc.expandtabs()
    found = []
    if names:
        params = _section(doc, "Parameters")
        if params is None:
            found.append(Finding(where, "no Parameters section"))
        else:
            named = _documented_names(params + (_section(doc, "Other Parameters") or ""))
            documented = named | {n.lstrip("*") for n in named}
            missing = [n for n in names if n not in documented and n.lstrip("*") not in documented]
            if missing:
                found.append(Finding(where, f"Parameters does not name {', '.join(missing)}"))
    value, gen = _returns_value(fn)
    if value:
        want = "Yields" if gen else "Returns"
        if _section(doc, want) is None and _section(doc, "Returns") is None:
            found.append(Finding(where, f"no {want} section"))
    return found


def missing_sections(path: Path) -> list[Finding]:
    """Public functions and methods of ``path`` whose docstring lacks a section or a parameter."""
    return missing_sections_in(path.read_text(encoding="utf-8"), path.relative_to(CALIB).as_posix())


def missing_sections_in(source: str, rel: str) -> list[Finding]:
    """Public functions and methods of the module ``source`` (named ``rel``) lacking a section or a parameter."""
    tree = ast.parse(source)
    found: list[Finding] = []
    for node in tree.body:
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and not node.name.startswith("_"):
            found += _check_function(node, f"{rel}:{node.lineno} {node.name}", method=False)
        elif isinstance(node, ast.ClassDef) and not node.name.startswith("_"):
            for item in node.body:
                if isinstance(item, (ast.FunctionDef, ast.AsyncFunctionDef)) and not item.name.startswith("_"):
                    found += _check_function(item, f"{rel}:{item.lineno} {node.name}.{item.name}", method=True)
    return found


def case_history(path: Path) -> list[Finding]:
    """Docstrings of ``path`` that carry a date, an issue number or a commit id."""
    return case_history_in(path.read_text(encoding="utf-8"), path.relative_to(CALIB).as_posix())


def case_history_in(source: str, rel: str) -> list[Finding]:
    """Docstrings of the module ``source`` (named ``rel``) that carry a date, an issue number or a commit id."""
    tree = ast.parse(source)
    found: list[Finding] = []
    for node in ast.walk(tree):
        if not isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)):
            continue
        doc = ast.get_docstring(node, clean=False)
        if not doc:
            continue
        where = f"{rel}:{getattr(node, 'lineno', 1)} {getattr(node, 'name', '<module>')}"
        for rx, what in ((_DATE, "a date"), (_ISSUE, "an issue number")):
            m = rx.search(doc)
            if m:
                found.append(Finding(where, f"{what}: {m.group(0)!r}"))
        ids = [w for w in _HEX.findall(doc) if _is_commit_id(w)]
        if ids:
            found.append(Finding(where, f"a commit id: {ids[0]!r}"))
    return found


FILES = calib_files()


@pytest.mark.parametrize("path", FILES, ids=[p.relative_to(CALIB).as_posix() for p in FILES])
def test_public_functions_have_numpydoc_sections(path: Path) -> None:
    found = missing_sections(path)
    assert not found, "numpydoc sections missing:\n" + "\n".join(f"  {f.where}: {f.what}" for f in found)


@pytest.mark.parametrize("path", FILES, ids=[p.relative_to(CALIB).as_posix() for p in FILES])
def test_docstrings_tell_no_case_history(path: Path) -> None:
    found = case_history(path)
    assert not found, "case history in docstrings:\n" + "\n".join(f"  {f.where}: {f.what}" for f in found)


def test_checker_sees_a_missing_section_and_a_date() -> None:
    """The checker itself: a bare function and a dated docstring are caught, a complete one passes."""
    src = (
        '"""Module, measured on 2024-01-31 at abc1234f for issue 7."""\n'
        "def f(x_m: float) -> float:\n"
        '    """Twice x."""\n'
        "    return 2 * x_m\n"
        "def g(x_m: float, y_m: float) -> float:\n"
        '    """Sum.\n\n    Parameters\n    ----------\n    x_m, y_m : float\n        Lengths (metres).\n\n'
        '    Returns\n    -------\n    float\n        Their sum (metres).\n    """\n'
        "    return x_m + y_m\n"
        "def h(x_m: float) -> None:\n"
        '    """Nothing.\n\n    Parameters\n    ----------\n    y : float\n        Not the argument.\n    """\n'
    )
    found = missing_sections_in(src, "probe.py") + case_history_in(src, "probe.py")
    whats = {f.where.split()[-1] + ": " + f.what.split(":")[0] for f in found}
    assert whats == {
        "f: no Parameters section",
        "f: no Returns section",
        "h: Parameters does not name x_m",
        "<module>: a date",
        "<module>: an issue number",
        "<module>: a commit id",
    }


def main() -> int:
    """Print, per file of ``calib``, the public functions lacking a section; return the total count."""
    total = 0
    for path in FILES:
        found = missing_sections(path)
        bad = {f.where for f in found}
        history = case_history(path)
        total += len(bad)
        print(f"{len(bad):4d} {len(history):3d}  {path.relative_to(CALIB).as_posix()}")
    print(f"{total:4d}       total (public functions lacking Parameters/Returns; then case-history docstrings)")
    return total


if __name__ == "__main__":
    sys.exit(0 if main() == 0 else 1)

"""calib is pure computation: it imports neither drivers nor service; drivers never import service;
production code never imports the simulated hardware except through configuration (lazy imports)."""

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _imports(path: Path) -> list[tuple[str, bool]]:
    """(module, at_top_level) for every import in a file."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    out = []
    top = set(map(id, tree.body))
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [(a.name, id(node) in top) for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            out.append((node.module, id(node) in top))
    return out


def test_calib_imports_neither_drivers_nor_service():
    bad = [
        (str(p.relative_to(ROOT)), m)
        for p in (ROOT / "calib").rglob("*.py")
        for m, _ in _imports(p)
        if m.split(".")[0] in ("drivers", "service")
    ]
    assert not bad, bad


def test_drivers_do_not_import_service():
    bad = [
        (str(p.relative_to(ROOT)), m)
        for p in (ROOT / "drivers").rglob("*.py")
        for m, _ in _imports(p)
        if m.split(".")[0] == "service"
    ]
    assert not bad, bad


def test_production_drivers_import_sim_only_lazily():
    bad = []
    for p in (ROOT / "drivers").rglob("*.py"):
        if "sim" in p.relative_to(ROOT / "drivers").parts:
            continue
        bad += [(str(p.relative_to(ROOT)), m) for m, top in _imports(p) if m.startswith("drivers.sim") and top]
    assert not bad, bad


def test_import_linter_contracts(tmp_path):
    import shutil
    import subprocess
    import sys

    exe = shutil.which("lint-imports", path=str(Path(sys.executable).parent)) or shutil.which("lint-imports")
    if exe is None:  # pragma: no cover - installed by the test extra
        import pytest

        pytest.skip("import-linter is not installed")
    res = subprocess.run([exe], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stdout + res.stderr

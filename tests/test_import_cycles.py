"""No import cycle between the project's modules, function-level imports included (grimp reads every import
statement of a module, wherever it sits): arrows only point down the data flow."""

import grimp
import numpy as np
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import connected_components

PACKAGES = ("calib", "drivers", "service", "i4cal")


def import_cycles(graph) -> list[list[str]]:
    """The strongly connected groups of more than one module of an import graph, each sorted."""
    modules = sorted(graph.modules)
    index = {m: i for i, m in enumerate(modules)}
    edges = [(index[m], index[d]) for m in modules for d in graph.find_modules_directly_imported_by(m) if d in index]
    rows, cols = zip(*edges, strict=True) if edges else ((), ())
    adjacency = csr_matrix((np.ones(len(rows)), (rows, cols)), shape=(len(modules), len(modules)))
    _, labels = connected_components(adjacency, directed=True, connection="strong")
    groups: dict[int, list[str]] = {}
    for module, label in zip(modules, labels, strict=True):
        groups.setdefault(int(label), []).append(module)
    return sorted(g for g in groups.values() if len(g) > 1)


def test_the_cycle_finder_finds_a_cycle():
    graph = grimp.ImportGraph()
    for m in ("p", "p.a", "p.b", "p.c"):
        graph.add_module(m)
    graph.add_import(importer="p.a", imported="p.b")
    graph.add_import(importer="p.b", imported="p.a")
    graph.add_import(importer="p.c", imported="p.a")
    assert import_cycles(graph) == [["p.a", "p.b"]]


def test_no_import_cycle_between_modules():
    cycles = import_cycles(grimp.build_graph(*PACKAGES))
    assert not cycles, f"import cycles: {cycles}"

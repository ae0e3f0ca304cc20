"""The import graph: no circles inside the core or the built-in plugins, and the core imports no plugin.

The graph is built by grimp from the source, with the imports made inside functions and under
``TYPE_CHECKING`` counted too: a circle that only a lazy import closes still ties two modules into
one, and the core stays small only while it needs nothing from the plugins.
"""

from __future__ import annotations

import grimp
import pytest

PACKAGES = ("artclass_core", "artclass_plugins")


@pytest.fixture(scope="module")
def graph():
    return grimp.build_graph(*PACKAGES, exclude_type_checking_imports=False)


def circles(graph) -> list[str]:
    """Every circle, as the chain of modules from an import back to its importer."""
    found = set()
    for importer in graph.modules:
        for imported in graph.find_modules_directly_imported_by(importer):
            if graph.chain_exists(importer=imported, imported=importer):
                chain = graph.find_shortest_chain(importer=imported, imported=importer)
                found.add(" -> ".join((importer, *chain)))
    return sorted(found)


def test_no_import_circles(graph):
    found = circles(graph)
    assert not found, "import circles (break each, e.g. by moving what both need into a third module):\n" + (
        "\n".join(found)
    )


def test_a_circle_is_found():
    """The check itself: a circle added to the graph is reported, with its modules in order."""
    graph = grimp.build_graph(*PACKAGES, exclude_type_checking_imports=False)
    graph.add_import(importer="artclass_core.errors", imported="artclass_core.cli")
    found = circles(graph)
    assert any(
        c.startswith("artclass_core.errors -> artclass_core.cli") and c.endswith("errors") for c in found
    )


def test_the_core_imports_no_plugin(graph):
    assert not graph.chain_exists(importer="artclass_core", imported="artclass_plugins", as_packages=True), (
        graph.find_shortest_chains(importer="artclass_core", imported="artclass_plugins")
    )

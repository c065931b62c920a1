"""The package's shape: imports run one way, with no circle, and no private name crosses a module.

The layer order itself is import-linter's contract in pyproject.toml (``make lint``); these tests
check what a contract cannot say.
"""
import ast
import pathlib

import pytest

import inject

PACKAGE = pathlib.Path(inject.__file__).parent


def _modules():
    for path in sorted(PACKAGE.rglob("*.py")):
        parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
        name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        yield name, path


def _imports(name, path):
    """(imported module, imported names) of every ``from X import ...`` in a module, relative
    imports resolved."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - node.level + 1]
                module = ".".join(base + ([node.module] if node.module else []))
            else:
                module = node.module or ""
            yield module, [alias.name for alias in node.names]


def test_no_private_name_is_imported_across_modules():
    crossings = [f"{name} imports {module}.{n}"
                 for name, path in _modules() for module, names in _imports(name, path)
                 if module.split(".")[0] == "inject" and module != name
                 for n in names if n.startswith("_") and not n.startswith("__")]
    assert crossings == []


def test_no_import_circle_inside_the_package():
    grimp = pytest.importorskip("grimp")
    graph = grimp.build_graph("inject")
    circles = set()
    for module in graph.modules:
        for imported in graph.find_modules_directly_imported_by(module):
            if graph.chain_exists(importer=imported, imported=module):
                circles.add(tuple(sorted((module, imported))))
    assert sorted(circles) == []


def test_the_public_api_resolves_every_name():
    """``inject.<name>`` for every name of ``inject.__all__`` (the lazy re-exports)."""
    missing = [name for name in inject.__all__ if not hasattr(inject, name)]
    assert missing == []
    with pytest.raises(AttributeError):
        inject.no_such_name  # noqa: B018


def test_the_stub_lists_the_lazy_api():
    """``inject/__init__.pyi`` (what type checkers and editors read in place of the lazy
    ``__getattr__``) imports each name of ``inject._API`` from the same module, and exports
    exactly ``inject.__all__``."""
    stub = ast.parse((PACKAGE / "__init__.pyi").read_text())
    imported = {alias.name: node.module for node in stub.body
                if isinstance(node, ast.ImportFrom) for alias in node.names}
    assert imported == inject._API
    exported = next(node.value for node in stub.body if isinstance(node, ast.Assign)
                    and [t.id for t in node.targets] == ["__all__"])
    assert ast.literal_eval(exported) == inject.__all__
    assert any(isinstance(node, ast.AnnAssign) and node.target.id == "__version__"
               for node in stub.body)


def test_the_package_is_typed():
    """``py.typed`` marks the package's annotations (and the stub) as meant for type checkers."""
    assert (PACKAGE / "py.typed").is_file()

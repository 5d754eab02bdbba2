"""The import graph of jaxcal, read with `ast` (imports inside functions included): no cycles and no
private names taken from another module, in the packages listed in CHECKED (the whole package). Run as a
script to print every offender."""

from __future__ import annotations

import ast
import pathlib

ROOT = pathlib.Path(__file__).resolve().parents[1] / "jaxcal"
CHECKED = ("jaxcal",)  # the whole package


def module_name(path: pathlib.Path) -> str:
    parts = path.relative_to(ROOT.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def sources() -> dict[str, ast.Module]:
    """Every module of the package, parsed, by dotted name."""
    return {module_name(p): ast.parse(p.read_text(), str(p)) for p in sorted(ROOT.rglob("*.py"))}


def is_package(name: str) -> bool:
    return (ROOT.parent / name.replace(".", "/") / "__init__.py").exists()


def base_of(node: ast.ImportFrom, importer: str) -> str:
    """The absolute module named by a `from ... import` (relative imports resolved)."""
    if not node.level:
        return node.module or ""
    package = importer if is_package(importer) else importer.rpartition(".")[0]
    for _ in range(node.level - 1):
        package = package.rpartition(".")[0]
    return f"{package}.{node.module}" if node.module else package


def imports(importer: str, tree: ast.Module, modules) -> list[tuple[str, str | None]]:
    """(module imported, name taken from it or None) for every jaxcal import in a module."""
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [(a.name, None) for a in node.names if a.name in modules]
        elif isinstance(node, ast.ImportFrom):
            base = base_of(node, importer)
            if base not in modules:
                continue
            for a in node.names:
                sub = f"{base}.{a.name}"
                found.append((sub, None) if sub in modules else (base, a.name))
    return found


def private_attributes(tree: ast.Module, aliases: dict[str, str]) -> list[tuple[str, str]]:
    """(module, name) for every `alias._name` where alias is a jaxcal module bound by an import."""
    return [(aliases[n.value.id], n.attr) for n in ast.walk(tree)
            if isinstance(n, ast.Attribute) and isinstance(n.value, ast.Name) and n.value.id in aliases
            and n.attr.startswith("_") and not n.attr.startswith("__")]


def module_aliases(importer: str, tree: ast.Module, modules) -> dict[str, str]:
    """Local names bound to jaxcal modules (`import jaxcal.x as m`, `from jaxcal import x`)."""
    bound = {}
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            bound |= {a.asname: a.name for a in node.names if a.asname and a.name in modules}
        elif isinstance(node, ast.ImportFrom) and base_of(node, importer) in modules:
            base = base_of(node, importer)
            bound |= {a.asname or a.name: f"{base}.{a.name}" for a in node.names if f"{base}.{a.name}" in modules}
    return bound


def graph(trees) -> dict[str, set[str]]:
    """Module -> modules it imports (anywhere in its body)."""
    return {m: {dst for dst, _ in imports(m, t, trees)} - {m} for m, t in trees.items()}


def in_checked(module: str) -> bool:
    return any(module == p or module.startswith(p + ".") for p in CHECKED)


def cycles(edges: dict[str, set[str]], keep) -> list[list[str]]:
    """Strongly connected components with more than one module, over the modules where keep is true."""
    nodes = [m for m in edges if keep(m)]
    index, low, stack, on_stack, found = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in (w for w in edges[v] if keep(w)):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while not component or component[-1] != v:
                component.append(stack.pop())
                on_stack.discard(component[-1])
            if len(component) > 1:
                found.append(sorted(component))

    for v in nodes:
        if v not in index:
            visit(v)
    return found


def own_package(module: str) -> str:
    """The package whose private modules a module may import: itself or its parent."""
    return module if is_package(module) else module.rpartition(".")[0]


def private_uses(trees) -> list[tuple[str, str, str]]:
    """(importer, module, name) for each private name one jaxcal module takes from another."""
    out = []
    for m, t in trees.items():
        taken = [(src, name) for src, name in imports(m, t, trees) if name is not None]
        taken += private_attributes(t, module_aliases(m, t, trees))
        taken += [(src, src.rpartition(".")[2]) for src, name in imports(m, t, trees)
                  if name is None and src.rpartition(".")[0] != own_package(m)]
        out += [(m, src, name) for src, name in taken if name.startswith("_") and not name.startswith("__") and src != m]
    return sorted(set(out))


def test_checked_packages_have_no_import_cycle():
    assert cycles(graph(sources()), in_checked) == []


def test_checked_packages_import_no_private_name():
    """Between checked modules only: a private name of an unchecked module is for its owners to publish."""
    offenders = private_uses(sources())
    others = [o for o in offenders if not (in_checked(o[0]) and in_checked(o[1]))]
    if others:
        print("private names still taken (not checked yet):", *others, sep="\n  ")
    assert [o for o in offenders if o not in others] == []


if __name__ == "__main__":
    trees = sources()
    print("cycles:", *cycles(graph(trees), lambda m: True), sep="\n  ")
    print("private names:", *private_uses(trees), sep="\n  ")

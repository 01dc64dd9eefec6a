"""The import rules of the layout (docs/architecture.md), checked on the source with ast.

- ``piezod.model`` is pure: numpy / scipy / math (and numba, which compiles the per-sample loops of
  ``piezod.model.kernels`` to machine code: computation only), no I/O module, nothing else of the
  host but ``piezod.errors``;
- ``firmware_proto`` and ``hil_sim`` import nothing from ``piezod`` (they stand on their own: the
  simulator stands in for hardware the host does not own);
- the host imports ``hil_sim`` only through ``piezod.simulator`` (used when the user asks for it);
- no import cycles between modules (imports inside functions count: a lazy import is a dependency).
"""

from __future__ import annotations

import ast
from collections.abc import Iterator
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("piezod", "hil_sim", "firmware_proto")

#: I/O (and other side-effect) modules the pure model may not import.
IO_MODULES = frozenset(
    {
        "asyncio",
        "fastapi",
        "http",
        "httpx",
        "io",
        "json",
        "logging",
        "matplotlib",
        "multiprocessing",
        "os",
        "pathlib",
        "pickle",
        "select",
        "serial",
        "shutil",
        "signal",
        "socket",
        "sqlite3",
        "subprocess",
        "sys",
        "tempfile",
        "threading",
        "time",
        "tqdm",
        "urllib",
        "usb",
        "uvicorn",
        "yaml",
    }
)


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


MODULES: dict[str, Path] = {
    _module_name(p): p for pkg in PACKAGES for p in sorted((ROOT / pkg).rglob("*.py"))
}


def _imports(name: str) -> Iterator[str]:
    """Every module ``name`` imports (also inside functions; not under ``if TYPE_CHECKING``)."""
    path = MODULES[name]
    package = name.split(".") if path.name == "__init__.py" else name.split(".")[:-1]

    def visit(node: ast.AST) -> Iterator[str]:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.If) and "TYPE_CHECKING" in ast.unparse(child.test):
                continue
            if isinstance(child, ast.Import):
                yield from (a.name for a in child.names)
            elif isinstance(child, ast.ImportFrom):
                if child.level:
                    base = package[: len(package) - (child.level - 1)]
                    mod = ".".join(base + ([child.module] if child.module else []))
                else:
                    mod = child.module or ""
                subs = [f"{mod}.{a.name}" for a in child.names if f"{mod}.{a.name}" in MODULES]
                if len(subs) < len(child.names):  # not only submodules: the module itself is used
                    yield mod
                yield from subs
            yield from visit(child)

    yield from visit(ast.parse(path.read_text(encoding="utf-8")))


def _violations(prefix: str, forbidden: tuple[str, ...]) -> dict[str, set[str]]:
    out: dict[str, set[str]] = {}
    for name in MODULES:
        if name == prefix or name.startswith(prefix + "."):
            bad = {i for i in _imports(name) if i.split(".")[0] in forbidden}
            if bad:
                out[name] = bad
    return out


def test_the_model_is_pure() -> None:
    bad: dict[str, set[str]] = {}
    for name in MODULES:
        if name.startswith("piezod.model"):
            for imp in _imports(name):
                top = imp.split(".")[0]
                host = top == "piezod" and not imp.startswith(("piezod.model", "piezod.errors"))
                if top in IO_MODULES or host:
                    bad.setdefault(name, set()).add(imp)
    assert not bad


def test_firmware_proto_stands_on_its_own() -> None:
    assert not _violations("firmware_proto", ("piezod", "hil_sim"))


def test_hil_sim_imports_nothing_of_the_host() -> None:
    assert not _violations("hil_sim", ("piezod",))


def test_the_host_reaches_the_simulator_through_one_entry_point() -> None:
    users = {n for n in _violations("piezod", ("hil_sim",))}
    assert users == {"piezod.simulator"}


def _resolve(imp: str) -> str | None:
    parts = imp.split(".")
    while parts and ".".join(parts) not in MODULES:
        parts.pop()
    return ".".join(parts) or None


def test_no_import_cycles() -> None:
    graph = {n: {m for i in _imports(n) if (m := _resolve(i)) and m != n} for n in MODULES}
    # Tarjan's strongly connected components (iterative): any component of size > 1 is a cycle.
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    cycles: list[list[str]] = []
    for root in graph:
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on_stack.add(root)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = len(index)
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph[child]))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                comp = []
                while True:
                    m = stack.pop()
                    on_stack.discard(m)
                    comp.append(m)
                    if m == node:
                        break
                if len(comp) > 1:
                    cycles.append(sorted(comp))
    assert not cycles

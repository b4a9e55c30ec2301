"""The rooms' one-way flow, read from the source (every import, module-level and inside functions,
from the AST; type-checking-only imports aside; nothing imported, nothing built): models < codegen < runtime < scenarios, a room imports
only itself and the rooms before it; codegen and runtime never import a paper model; no two modules
import each other, directly or round a longer cycle."""
import ast
from functools import lru_cache
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
ROOMS = ("models", "codegen", "runtime", "scenarios")
#: The paper models (symkf.models.<name> and anything under it): the experiments' business, not the toolchain's.
PAPER_MODELS = ("launcher", "attitude", "geo_satellite", "marg", "marg_ekf", "marg_mekf")


def _module_name(room: str, path: Path) -> str:
    parts = path.relative_to(ROOT / room).with_suffix("").parts
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(("symkf", room, *parts))


@lru_cache(maxsize=None)
def modules() -> dict[str, Path]:
    """{module name: file} of every module of the four rooms."""
    return {_module_name(room, path): path for room in ROOMS for path in sorted((ROOT / room).rglob("*.py"))
            if "__pycache__" not in path.parts}


def _resolve(module: str, path: Path, node: ast.ImportFrom) -> str:
    """The absolute module of a ``from ... import`` (relative imports resolved against ``module``)."""
    if not node.level:
        return node.module or ""
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    for _ in range(node.level - 1):
        package = package.rpartition(".")[0]
    return f"{package}.{node.module}" if node.module else package


def _type_checking_imports(tree: ast.Module) -> set[int]:
    """Imports under ``if TYPE_CHECKING:``: read by type checkers only, never executed."""
    guarded = [node for node in ast.walk(tree) if isinstance(node, ast.If)
               and (getattr(node.test, "id", None) == "TYPE_CHECKING" or getattr(node.test, "attr", None) == "TYPE_CHECKING")]
    return {id(inner) for node in guarded for statement in node.body for inner in ast.walk(statement)}


@lru_cache(maxsize=None)
def imports() -> dict[str, tuple[tuple[str, int], ...]]:
    """{module: ((imported symkf module, line), ...)}: ``from pkg import name`` counts as an import
    of ``pkg.name`` when that is a module of the rooms, else of ``pkg``."""
    known = modules()
    out = {}
    for module, path in known.items():
        found = []
        tree = ast.parse(path.read_text(encoding="utf-8"), str(path))
        type_only = _type_checking_imports(tree)
        for node in ast.walk(tree):
            if id(node) in type_only:
                continue
            if isinstance(node, ast.Import):
                found += [(alias.name, node.lineno) for alias in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = _resolve(module, path, node)
                found += [(f"{base}.{alias.name}" if f"{base}.{alias.name}" in known else base, node.lineno)
                          for alias in node.names]
        out[module] = tuple(dict.fromkeys((name, line) for name, line in found
                                          if name == "symkf" or name.startswith("symkf.")))
    return out


def _room(module: str) -> str | None:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 and parts[1] in ROOMS else None


def _where(module: str, line: int) -> str:
    return f"{modules()[module].relative_to(ROOT)}:{line}"


def test_a_room_imports_only_itself_and_the_rooms_before_it():
    violations = [f"{_where(module, line)} ({_room(module)}) imports {target} ({_room(target)})"
                  for module, targets in imports().items() for target, line in targets
                  if _room(target) and ROOMS.index(_room(target)) > ROOMS.index(_room(module))]
    assert not violations, "imports up a room:\n" + "\n".join(violations)


def test_codegen_and_runtime_import_no_paper_model():
    paper = tuple(f"symkf.models.{name}" for name in PAPER_MODELS)
    violations = [f"{_where(module, line)} imports {target}"
                  for module, targets in imports().items() if _room(module) in ("codegen", "runtime")
                  for target, line in targets if target in paper or target.startswith(tuple(p + "." for p in paper))]
    assert not violations, "the toolchain imports a paper model:\n" + "\n".join(violations)


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan, iterative)."""
    index, low, on_stack, stack, out, counter = {}, {}, set(), [], [], [0]
    for root in sorted(graph):
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = counter[0]
        counter[0] += 1
        stack.append(root)
        on_stack.add(root)
        while work:
            node, children = work[-1]
            for child in children:
                if child not in index:
                    index[child] = low[child] = counter[0]
                    counter[0] += 1
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph[child]))))
                    break
                if child in on_stack:
                    low[node] = min(low[node], index[child])
            else:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[node])
                if low[node] == index[node]:
                    component = []
                    while True:
                        member = stack.pop()
                        on_stack.discard(member)
                        component.append(member)
                        if member == node:
                            break
                    if len(component) > 1:
                        out.append(sorted(component))
    return out


def test_no_import_cycle():
    known = modules()
    graph = {module: {target for target, _ in targets if target in known and target != module}
             for module, targets in imports().items()}
    cycles = _cycles(graph)
    assert not cycles, "import cycles (module-level and function-level imports):\n" + "\n".join(
        " <-> ".join(cycle) for cycle in cycles)


#: Past these sizes a file or class is doing several jobs.
MAX_FILE_LINES, MAX_CLASS_LINES = 600, 300


def test_no_file_or_class_too_large_to_read():
    too_large = []
    for module, path in modules().items():
        lines = path.read_text(encoding="utf-8").splitlines()
        if len(lines) > MAX_FILE_LINES:
            too_large.append(f"{path.relative_to(ROOT)}: {len(lines)} lines")
        for node in ast.walk(ast.parse("\n".join(lines), str(path))):
            if isinstance(node, ast.ClassDef) and node.end_lineno - node.lineno + 1 > MAX_CLASS_LINES:
                too_large.append(f"{path.relative_to(ROOT)}: class {node.name} {node.end_lineno - node.lineno + 1} lines")
    assert not too_large, f"over {MAX_FILE_LINES} lines a file or {MAX_CLASS_LINES} a class:\n" + "\n".join(too_large)

"""The house's floors: no import cycle, no upward import, no torch in the floor or the generator,
and no module importing a command module.

Floors, bottom to top: c4d_core <- datagen <- dynpt <- c4d_pipeline <- c4d (the roof). Every
import counts, whether at module level, inside a function or under `if TYPE_CHECKING:`; the one
exception is an `if __name__ == "__main__":` block, which runs only when its file is the program
(`torchrun -m dynpt.cli_train` enters through the roof's `c4d.cli.main`), so no importer depends on
it. A command module (`cli`, `cli_*`: `add_arguments` and `run` of one subcommand) is imported by
no module: the dispatcher `c4d.cli` loads the chosen one by name, and what other modules need
lives in a library module beside it (`c4d_pipeline.eval_recon` for `cli_eval_recon`). The one command
module that may be imported is the dispatcher itself (by `c4d/__main__.py`). Modules are read with
`ast`, never imported.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
FLOORS = ["c4d_core", "datagen", "dynpt", "c4d_pipeline", "c4d"]  # bottom first
TORCH_FREE = {"c4d_core", "datagen"}
DISPATCHER = "c4d.cli"


def module_files(root: Path, packages: list[str]) -> dict[str, Path]:
    """Dotted module name -> file for every .py file of `packages` under `root`."""
    modules = {}
    for package in packages:
        for path in sorted((root / package).rglob("*.py")):
            parts = list(path.relative_to(root).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts.pop()
            modules[".".join(parts)] = path
    return modules


def _is_main_block(node: ast.AST) -> bool:
    """`if __name__ == "__main__":`."""
    return (isinstance(node, ast.If) and isinstance(node.test, ast.Compare)
            and isinstance(node.test.left, ast.Name) and node.test.left.id == "__name__"
            and any(isinstance(c, ast.Constant) and c.value == "__main__" for c in node.test.comparators))


def imported_names(path: Path, module: str) -> list[tuple[str, int]]:
    """(dotted name, line) of every import in the file, `from X import Y` giving X.Y and X.

    Relative imports are resolved against `module`; `__main__` blocks are left out.
    """
    tree = ast.parse(path.read_text(), filename=str(path))
    is_package = path.name == "__init__.py"
    skipped = {id(n) for block in ast.walk(tree) if _is_main_block(block) for n in ast.walk(block)}
    names = []
    for node in ast.walk(tree):
        if id(node) in skipped:
            continue
        if isinstance(node, ast.Import):
            names += [(alias.name, node.lineno) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = module.split(".")[: len(module.split(".")) - node.level + is_package]
                base = ".".join(anchor + ([base] if base else []))
            names.append((base, node.lineno))
            names += [(f"{base}.{alias.name}", node.lineno) for alias in node.names]
    return names


def import_graph(root: Path, packages: list[str]):
    """Edges module -> project module it imports, with the line: {(importer, imported): line}."""
    modules = module_files(root, packages)
    edges, external = {}, {}
    for module, path in modules.items():
        for name, line in imported_names(path, module):
            if name in modules:
                if name != module:
                    edges.setdefault((module, name), line)
            else:
                external.setdefault(module, set()).add(name.split(".")[0])
    return modules, edges, external


def find_cycles(nodes, edges) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan), each sorted."""
    successors = {n: [] for n in nodes}
    for a, b in edges:
        successors[a].append(b)
    index, low, stack, on_stack, cycles = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in successors[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                cycles.append(sorted(component))

    for v in nodes:
        if v not in index:
            visit(v)
    return cycles


def is_command_module(module: str) -> bool:
    """`datagen.cli`, `dynpt.cli_train`, `c4d.inspect.cli`, ...: a subcommand's module."""
    last = module.rsplit(".", 1)[-1]
    return last == "cli" or last.startswith("cli_")


def violations(root: Path, packages: list[str] = FLOORS, torch_free: set[str] = TORCH_FREE,
               dispatcher: str = DISPATCHER) -> list[str]:
    """Every broken rule, one readable line each (empty when the house stands)."""
    modules, edges, external = import_graph(root, packages)
    floor = {m: packages.index(m.split(".")[0]) for m in modules}
    problems = [f"import cycle: {' <-> '.join(c)}" for c in find_cycles(modules, edges)]
    for (a, b), line in sorted(edges.items()):
        if floor[b] > floor[a]:
            problems.append(f"upward import: {a} (line {line}) imports {b}")
        if is_command_module(b) and b != dispatcher:
            problems.append(f"command module imported: {a} (line {line}) imports {b}")
    for module, names in sorted(external.items()):
        if module.split(".")[0] in torch_free and "torch" in names:
            problems.append(f"torch imported by {module}")
    return problems


def test_the_project_has_no_cycle_no_upward_import_and_no_torch_in_the_floor():
    assert violations(ROOT) == []


def test_every_floor_is_a_package_of_the_project():
    modules = module_files(ROOT, FLOORS)
    assert {m.split(".")[0] for m in modules} == set(FLOORS)
    assert "c4d_core.config" in modules and "c4d.cli" in modules


@pytest.mark.parametrize("files, expected", [
    ({"low/a.py": "def f():\n    from low import b\n", "low/b.py": "from low.a import f\n"},
     "import cycle: low.a <-> low.b"),
    ({"low/a.py": "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from high.c import X\n",
      "high/c.py": "X = 1\n"},
     "upward import: low.a (line 3) imports high.c"),
    ({"low/a.py": "def f():\n    import torch.nn\n"}, "torch imported by low.a"),
    ({"high/c.py": "from . import d\n", "high/d.py": "from .c import X\n"},
     "import cycle: high.c <-> high.d"),
    ({"high/cli_x.py": "def run(args):\n    pass\n", "high/report.py": "def f():\n    from high import cli_x\n"},
     "command module imported: high.report (line 2) imports high.cli_x"),
])
def test_the_checker_catches_each_kind_of_violation(tmp_path, files, expected):
    for name, text in {"low/__init__.py": "", "high/__init__.py": "", **files}.items():
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / name).write_text(text)
    assert expected in violations(tmp_path, ["low", "high"], torch_free={"low"})


def test_only_the_dispatcher_is_an_importable_command_module(tmp_path):
    for name, text in {"low/__init__.py": "", "low/cli.py": "def run(args):\n    pass\n",
                       "high/__init__.py": "", "high/cli.py": "X = 1\n",
                       "high/__main__.py": "from high.cli import X\n", "high/client.py": "from low import cli\n"}.items():
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / name).write_text(text)
    assert violations(tmp_path, ["low", "high"], dispatcher="high.cli") == [
        "command module imported: high.client (line 1) imports low.cli"]


def test_a_main_block_is_not_an_import_of_the_module(tmp_path):
    (tmp_path / "low").mkdir()
    (tmp_path / "high").mkdir()
    (tmp_path / "low/a.py").write_text('if __name__ == "__main__":\n    from high.c import main\n')
    (tmp_path / "high/c.py").write_text("def main():\n    pass\n")
    assert violations(tmp_path, ["low", "high"]) == []

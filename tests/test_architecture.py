"""The layers of docs/architecture.md hold: commands (humotion/cli.py and every */command.py) call
libraries, never the reverse; only the cli imports the commands (a command importing the cli, or
another command, makes a cycle through it); no module imports from a layer above its own; humotion's
modules import each other without cycles; no module reaches into another's private names (a leading
underscore); libraries do not import click and do not print.

The import graph is read from the source (an AST walk of every module under humotion/), so an
import inside a function counts as much as one at the top of a file; cycles are looked for among
module-level imports (those that run when a module is imported; `if TYPE_CHECKING:` blocks do not).
"""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

from humotion.data import default_data_dir

PACKAGE = Path(__file__).resolve().parents[1] / "humotion"


def module_name(path: Path, root: Path = PACKAGE) -> str:
    parts = ("humotion",) + path.relative_to(root).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


LAYERS = [
    ("core", ["humotion", "humotion.motion", "humotion.skeleton", "humotion.rotations", "humotion.model_files",
              "humotion.optimize", "humotion.assets", "humotion.atomic"]),
    ("the canonical body", ["humotion.canonical", "humotion.retarget.keyjoints"]),
    ("files", ["humotion.io"]),
    ("data", ["humotion.data", "humotion.training"]),
    ("systems", ["humotion.sparse", "humotion.capture", "humotion.retarget", "humotion.body", "humotion.live"]),
    ("viewer", ["humotion.viewer"]),
    ("commands", ["humotion.cli", "humotion.options", "humotion.outputs"]),
]
"""docs/architecture.md's layers, bottom up: a module imports from its own layer and those below.
A package names its subpackages too; the longest name that matches a module wins."""


def is_command(module: str) -> bool:
    return module == "humotion.cli" or module.endswith(".command")


def layer(module: str) -> int:
    """The index in LAYERS of the module's layer (commands: the top); KeyError for a module of none."""
    if is_command(module):
        return len(LAYERS) - 1
    matches = [(len(name), i) for i, (_, names) in enumerate(LAYERS) for name in names
               if module == name or module.startswith(name + ".")]
    if not matches:
        raise KeyError(f"{module} is in no layer of LAYERS: add it there and to docs/architecture.md")
    return max(matches)[1]


def _type_checking(node: ast.If) -> bool:
    return "TYPE_CHECKING" in ast.unparse(node.test)


def imports(path: Path, modules: set[str], root: Path = PACKAGE) -> list[tuple[str, bool]]:
    """(imported humotion module, whether the import runs at module level) for each import in the
    file. `from a import b` names the module a.b when there is one, else a."""
    name = module_name(path, root)
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found: list[tuple[str, bool]] = []

    def visit(node: ast.AST, top: bool) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.Import):
                found.extend((a.name, top) for a in child.names if a.name.split(".")[0] == "humotion")
            elif isinstance(child, ast.ImportFrom):
                base = child.module or ""
                if child.level:   # relative: from . import x, from ..y import z
                    anchor = package.split(".")[: len(package.split(".")) - child.level + 1]
                    base = ".".join(anchor + ([base] if base else []))
                if base.split(".")[0] == "humotion":
                    for alias in child.names:
                        sub = f"{base}.{alias.name}"
                        found.append((sub if sub in modules else base, top))
            elif isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)):
                visit(child, False)
            elif isinstance(child, ast.If) and _type_checking(child):
                visit(child, False)
            else:
                visit(child, top)

    visit(ast.parse(path.read_text(), str(path)), True)
    return found


def import_graph(root: Path = PACKAGE) -> dict[str, list[tuple[str, bool]]]:
    """Module -> its imports of humotion modules, for every module under root."""
    files = sorted(root.rglob("*.py"))
    modules = {module_name(f, root) for f in files}
    return {module_name(f, root): imports(f, modules, root) for f in files}


def imports_of_commands(graph) -> list[str]:
    """Imports of a command module by anything but humotion.cli, which wires the commands up."""
    return sorted({f"{a} imports {b}" for a, targets in graph.items() if a != "humotion.cli"
                   for b, _ in targets if is_command(b)})


def cycles(graph) -> list[list[str]]:
    """The import cycles among module-level imports: strongly connected components of more than one
    module, or a module importing itself (Tarjan's algorithm)."""
    edges = {a: sorted({b for b, top in targets if top and b in graph}) for a, targets in graph.items()}
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    found: list[list[str]] = []

    def connect(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in edges[v]:
            if w not in index:
                connect(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                component.append(w)
                if w == v:
                    break
            if len(component) > 1 or v in edges[v]:
                found.append(sorted(component))

    for v in edges:
        if v not in index:
            connect(v)
    return found


def private_uses(path: Path, modules: set[str], root: Path = PACKAGE) -> list[str]:
    """"module uses other._name" for each private name (one leading underscore; dunders such as
    __version__ are public) of another humotion module that the file imports (`from other import
    _name`) or reads off an imported module (`other._name`)."""
    name = module_name(path, root)
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    tree = ast.parse(path.read_text(), str(path))
    bound: dict[str, str] = {}   # local name -> the humotion module it is
    found = []

    def private(attribute: str) -> bool:
        return attribute.startswith("_") and not attribute.startswith("__")

    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            bound.update({a.asname or a.name: a.name for a in node.names if a.name.split(".")[0] == "humotion"})
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join(anchor + ([base] if base else []))
            if base.split(".")[0] != "humotion":
                continue
            for alias in node.names:
                if f"{base}.{alias.name}" in modules:
                    bound[alias.asname or alias.name] = f"{base}.{alias.name}"
                elif private(alias.name) and base != name:
                    found.append(f"{name} uses {base}.{alias.name}")
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute) and private(node.attr):
            owner = bound.get(ast.unparse(node.value))
            if owner is not None and owner != name:
                found.append(f"{name} uses {owner}.{node.attr}")
    return found


def private_uses_across_modules(root: Path = PACKAGE) -> list[str]:
    files = sorted(root.rglob("*.py"))
    modules = {module_name(f, root) for f in files}
    return sorted({use for f in files for use in private_uses(f, modules, root)})


def library_nodes(root: Path = PACKAGE):
    """(module name, AST node) for every node of every library module (each layer below the
    commands'), functions' bodies included."""
    for path in sorted(root.rglob("*.py")):
        name = module_name(path, root)
        if layer(name) < len(LAYERS) - 1:
            yield from ((name, node) for node in ast.walk(ast.parse(path.read_text(), str(path))))


def libraries_importing(package: str, root: Path = PACKAGE) -> list[str]:
    """The library modules that import `package` (a top-level name such as "click"), at module
    level or inside a function."""
    found = []
    for name, node in library_nodes(root):
        names = ([a.name for a in node.names] if isinstance(node, ast.Import)
                 else [node.module or ""] if isinstance(node, ast.ImportFrom) and not node.level else [])
        if any(n.split(".")[0] == package for n in names) and name not in found:
            found.append(name)
    return found


def libraries_printing(root: Path = PACKAGE) -> list[str]:
    """"module, line N" for each call of print() in a library module: libraries log or warn, and
    the command prints."""
    return [f"{name}, line {node.lineno}" for name, node in library_nodes(root)
            if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id == "print"]


def test_only_the_cli_imports_commands():
    assert imports_of_commands(import_graph()) == []


def test_no_module_imports_from_a_layer_above_its_own():
    graph = import_graph()
    upward = sorted({f"{a} ({LAYERS[layer(a)][0]}) imports {b} ({LAYERS[layer(b)][0]})"
                     for a, targets in graph.items()
                     for b, _ in targets if layer(b) > layer(a)})
    assert upward == []


def test_libraries_do_not_import_click():
    """Options, printing and exit codes are the commands' (docs/architecture.md)."""
    assert libraries_importing("click") == []


def test_libraries_do_not_print():
    """What a library has to say it logs (logging.getLogger("humotion....")) or warns; the command
    prints it (humotion.options.show_log)."""
    assert libraries_printing() == []


def test_a_library_printing_is_caught(tmp_path):
    root = _copy(tmp_path)
    (root / "io" / "intruder.py").write_text('"""print(this docstring is no call)"""\n\ndef f():\n    print("hello")\n')
    (root / "io" / "command.py").write_text('print("a command prints")\n')
    assert libraries_printing(root) == ["humotion.io.intruder, line 4"]


def intruder_root(tmp_path, source: str) -> Path:
    """A copy of the package with humotion/io/intruder.py holding source."""
    root = _copy(tmp_path)
    (root / "io" / "intruder.py").write_text(source)
    return root


@pytest.mark.parametrize("seam, source", [
    ("a module-level import", "import click\n"),
    ("a lazy import of a submodule", "def f():\n    from click.testing import CliRunner\n"),
])
def test_a_library_importing_click_is_caught(tmp_path, seam, source):
    assert "humotion.io.intruder" in libraries_importing("click", intruder_root(tmp_path, source)), seam


def test_no_import_cycles():
    assert cycles(import_graph()) == []


def test_the_import_graph_is_read_as_python_runs_it():
    graph = import_graph()
    assert ("humotion.body.export", True) in graph["humotion.body.command"]
    assert ("humotion.viewer", False) in graph["humotion.retarget.command"]   # inside the --view branch
    assert "humotion.cli" in graph and "humotion.no_such_module" not in graph


@pytest.mark.parametrize("seam, source", [
    ("a lazy import of a command", "def f():\n    from humotion.cli import main\n"),
    ("a module-level import of a command", "from humotion.body.command import body_command\n"),
])
def test_a_library_importing_a_command_is_caught(tmp_path, seam, source):
    graph = import_graph(intruder_root(tmp_path, source))
    assert imports_of_commands(graph) == [f"humotion.io.intruder imports {source.split()[-3]}"], seam


def test_a_command_importing_the_cli_is_caught(tmp_path):
    root = _copy(tmp_path)
    (root / "retarget" / "command.py").write_text("def view():\n    from humotion.cli import _serve\n")
    assert imports_of_commands(import_graph(root)) == ["humotion.retarget.command imports humotion.cli"]


def test_a_cycle_is_caught_and_an_import_inside_a_function_breaks_it(tmp_path):
    root = _copy(tmp_path)
    (root / "io" / "ping.py").write_text("from humotion.io import pong\n")
    (root / "io" / "pong.py").write_text("from humotion.io.ping import x\n")
    assert ["humotion.io.ping", "humotion.io.pong"] in cycles(import_graph(root))
    (root / "io" / "pong.py").write_text("def f():\n    from humotion.io.ping import x\n")
    assert cycles(import_graph(root)) == []


def test_no_module_uses_another_modules_private_names():
    """A helper several modules need is public in the module where it belongs (documented, with
    its shapes), not imported under its private name."""
    assert private_uses_across_modules() == []


@pytest.mark.parametrize("seam, source, use", [
    ("a private function", "from humotion.io.bvh import _Reader\n", "humotion.io.bvh._Reader"),
    ("a relative import", "def f():\n    from .bvh import _Reader\n", "humotion.io.bvh._Reader"),
    ("a module's attribute", "from humotion.io import bvh\nx = bvh._Reader\n", "humotion.io.bvh._Reader"),
    ("an imported module's attribute", "import humotion.io.bvh as b\nx = b._Reader\n", "humotion.io.bvh._Reader"),
])
def test_a_private_name_used_across_modules_is_caught(tmp_path, seam, source, use):
    root = _copy(tmp_path)
    (root / "io" / "intruder.py").write_text(source + "from humotion import __version__\n_own = 1\ny = _own\n")
    assert f"humotion.io.intruder uses {use}" in private_uses_across_modules(root), seam
    assert [u for u in private_uses_across_modules(root) if u.startswith("humotion.io.intruder")] == \
        [f"humotion.io.intruder uses {use}"], seam


def test_one_data_folder_setting(monkeypatch, tmp_path):
    """default_data_dir() reads $HUMOTION_DATA; no other module spells out ../shared/data."""
    monkeypatch.setenv("HUMOTION_DATA", str(tmp_path))
    assert default_data_dir() == tmp_path
    spelled = [str(f.relative_to(PACKAGE)) for f in PACKAGE.rglob("*.py")
               if '"shared" / "data"' in f.read_text() or "HUMOTION_DATA" in f.read_text()]
    assert spelled == ["data/root.py"]


def _copy(tmp_path: Path) -> Path:
    """The package's .py files copied under tmp_path/humotion (to plant an import in)."""
    root = tmp_path / "humotion"
    for f in PACKAGE.rglob("*.py"):
        (root / f.relative_to(PACKAGE)).parent.mkdir(parents=True, exist_ok=True)
        (root / f.relative_to(PACKAGE)).write_text(f.read_text())
    return root


def test_the_command_line_starts_without_the_heavy_solvers():
    """`humotion` imports capture's config to build its options; scipy.optimize (0.3-0.4 s of every
    start) is imported only where a track or a camera is solved."""
    probe = "import sys, humotion.cli; print('scipy.optimize' in sys.modules)"
    assert subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True).stdout.strip() == "False"

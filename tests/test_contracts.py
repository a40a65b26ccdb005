"""Import contracts (DESIGN.md section 2, issue 14 item 7), read from the source text with ``ast``:
imports at module level and inside functions, relative imports resolved, ``spdepth.acq.x`` and
``acq.x`` spellings alike, and constant-string ``importlib.import_module`` calls.

* recon imports nothing of acq, gui or drivers; drivers nothing of acq, recon or gui;
* gui never imports the CLI (acq.cli, acq.commands) and never mentions argparse;
* only the CLI (acq.cli, acq.commands) imports gui;
* no import cycles between files (a package's ``__init__`` importing its own submodules is fine);
* no ``redirect_stdout`` in acq (call the library, do not scrape a command's output).

The checker lives here, not in a tool outside the repository, because CI runs a clean clone. Each
rule is its own test and prints the offending lines; the last tests run the checker on a tiny
synthetic tree so that it cannot pass by seeing nothing.
"""

from __future__ import annotations

import ast
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
ROOMS = ("acq", "recon", "drivers", "gui")
CLI = ("acq.cli", "acq.commands")
"""The command-line front end: the only code that may import gui."""


@dataclass(frozen=True)
class Import:
    """One imported module, where it is written."""

    path: str          # file, relative to the tree's root
    line: int
    text: str          # the source line, stripped
    source: str        # importing module, e.g. "acq.distributed"
    target: str        # imported module without "spdepth.", e.g. "acq.commands.recon"
    in_function: bool

    def __str__(self) -> str:
        where = "  (in a function)" if self.in_function else ""
        return f"{self.path}:{self.line}: {self.text}{where}"


@dataclass
class Tree:
    root: Path
    modules: dict[str, Path]           # "acq.commands.scan" -> file
    imports: list[Import]              # imports of modules of the four rooms only
    lines: dict[str, list[str]]        # module -> its source lines

    def relpath(self, module: str) -> str:
        return self.modules[module].relative_to(self.root).as_posix()


def room_of(module: str) -> str:
    return module.split(".", 1)[0]


def is_within(module: str, package: str) -> bool:
    return module == package or module.startswith(package + ".")


def _module_name(root: Path, path: Path) -> str:
    parts = list(path.relative_to(root).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _normalise(name: str) -> str | None:
    """``spdepth.acq.x`` and ``acq.x`` -> ``acq.x``; anything outside the four rooms -> None."""
    parts = name.split(".")
    if parts[0] == "spdepth":
        parts = parts[1:]
    if not parts or parts[0] not in ROOMS:
        return None
    return ".".join(parts)


class _Collector(ast.NodeVisitor):
    def __init__(self, tree: Tree, module: str, is_package: bool):
        self.tree, self.module = tree, module
        self.package = module if is_package else module.rpartition(".")[0]
        self.depth = 0          # > 0 inside a function or lambda

    def _add(self, node: ast.AST, name: str | None) -> None:
        target = _normalise(name) if name else None
        if target is None:
            return
        lines = self.tree.lines[self.module]
        self.tree.imports.append(Import(self.tree.relpath(self.module), node.lineno,
                                        lines[node.lineno - 1].strip(), self.module, target,
                                        self.depth > 0))

    def _function(self, node) -> None:
        self.depth += 1
        self.generic_visit(node)
        self.depth -= 1

    visit_FunctionDef = visit_AsyncFunctionDef = visit_Lambda = _function

    def visit_Import(self, node: ast.Import) -> None:
        for alias in node.names:
            self._add(node, alias.name)

    def visit_ImportFrom(self, node: ast.ImportFrom) -> None:
        base = node.module or ""
        if node.level:
            up = self.package.split(".")
            up = up[:len(up) - (node.level - 1)]
            base = ".".join(up + ([base] if base else []))
        targets = []
        for alias in node.names:
            sub = _normalise(f"{base}.{alias.name}")
            # ``from pkg import submodule`` imports the submodule; ``from mod import name`` the module
            target = sub if sub in self.tree.modules else base
            if target not in targets:
                targets.append(target)
        for target in targets:
            self._add(node, target)

    def visit_Call(self, node: ast.Call) -> None:
        f = node.func
        name = f.attr if isinstance(f, ast.Attribute) else getattr(f, "id", "")
        if (name in ("import_module", "__import__") and node.args
                and isinstance(node.args[0], ast.Constant) and isinstance(node.args[0].value, str)):
            self._add(node, node.args[0].value)
        self.generic_visit(node)


def scan(root: Path = ROOT) -> Tree:
    """Every module of the four rooms under ``root`` and everything it imports from them."""
    files = sorted(p for room in ROOMS if (root / room).is_dir() for p in (root / room).rglob("*.py")
                   if "__pycache__" not in p.parts)
    tree = Tree(root, {_module_name(root, p): p for p in files}, [], {})
    for module, path in tree.modules.items():
        source = path.read_text(encoding="utf-8")
        tree.lines[module] = source.splitlines()
        _Collector(tree, module, path.name == "__init__.py").visit(ast.parse(source, str(path)))
    return tree


def imports_against_the_flow(tree: Tree, room: str, forbidden: tuple[str, ...]) -> list[Import]:
    return [i for i in tree.imports if room_of(i.source) == room and room_of(i.target) in forbidden]


def gui_imports_of_the_cli(tree: Tree) -> list[Import]:
    return [i for i in tree.imports
            if room_of(i.source) == "gui" and any(is_within(i.target, c) for c in CLI)]


def gui_importers_outside_the_cli(tree: Tree) -> list[Import]:
    return [i for i in tree.imports if room_of(i.target) == "gui" and room_of(i.source) != "gui"
            and not any(is_within(i.source, c) for c in CLI)]


def mentions(tree: Tree, room: str, word: str) -> list[str]:
    """Lines of ``room``'s files that hold ``word`` anywhere (code, string or comment)."""
    return [f"{tree.relpath(m)}:{n}: {line.strip()}" for m, lines in tree.lines.items()
            if room_of(m) == room for n, line in enumerate(lines, 1) if word in line]


def module_of(tree: Tree, target: str) -> str | None:
    """The file an import runs: ``target`` itself, or the closest package above it."""
    while target and target not in tree.modules:
        target = target.rpartition(".")[0]
    return target or None


def import_cycles(tree: Tree) -> list[tuple[list[str], list[Import]]]:
    """Groups of files that import each other (strongly connected components of the import graph,
    function-level imports included), each with the imports that tie it together. An import of a
    module's own package (``acq.commands.scan`` -> ``acq.commands``) is no edge: Python has run
    the package before the module, and the package may import its submodules."""
    edges: dict[str, dict[str, list[Import]]] = {m: {} for m in tree.modules}
    for i in tree.imports:
        dst = module_of(tree, i.target)
        if dst is None or dst == i.source or is_within(i.source, dst):
            continue
        edges[i.source].setdefault(dst, []).append(i)
    # Tarjan's algorithm, iterative (no recursion limit on a deep chain)
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    groups: list[list[str]] = []
    for start in sorted(edges):
        if start in index:
            continue
        work = [(start, iter(sorted(edges[start])))]
        index[start] = low[start] = len(index)
        stack.append(start)
        on_stack.add(start)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = len(index)
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(edges[child]))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                parent = work[-1][0]
                low[parent] = min(low[parent], low[node])
            if low[node] == index[node]:
                group = []
                while True:
                    m = stack.pop()
                    on_stack.discard(m)
                    group.append(m)
                    if m == node:
                        break
                if len(group) > 1:
                    groups.append(sorted(group))
    return [(g, [i for m in g for dst, imps in sorted(edges[m].items()) if dst in g for i in imps])
            for g in sorted(groups)]


def _report(title: str, offences) -> None:
    offences = list(offences)
    if offences:
        print(f"{title}: {len(offences)}")
        for o in offences:
            print(f"  {o}")
    assert not offences, f"{title} (the lines are in the captured stdout)"


@pytest.fixture(scope="module")
def tree() -> Tree:
    return scan(ROOT)


# ---- the rules ------------------------------------------------------------------------------------

def test_the_checker_sees_the_repository(tree):
    # a wrong ROOT or a broken walk would make every rule below pass on nothing
    assert {"acq.cli", "recon.estimate", "drivers.galvo.protocol", "gui.window"} <= set(tree.modules)
    assert len(tree.imports) > 100


def test_recon_imports_nothing_of_acq_gui_drivers(tree):
    _report("recon imports against the flow",
            imports_against_the_flow(tree, "recon", ("acq", "gui", "drivers")))


def test_drivers_import_nothing_of_acq_recon_gui(tree):
    _report("drivers imports against the flow",
            imports_against_the_flow(tree, "drivers", ("acq", "recon", "gui")))


def test_gui_never_imports_the_cli(tree):
    _report("gui imports of acq.cli / acq.commands", gui_imports_of_the_cli(tree))


def test_gui_never_mentions_argparse(tree):
    _report("gui lines mentioning argparse", mentions(tree, "gui", "argparse"))


def test_only_the_cli_imports_gui(tree):
    _report("imports of gui outside acq.cli / acq.commands", gui_importers_outside_the_cli(tree))


@pytest.mark.parametrize("room", ROOMS)
def test_no_import_cycles(tree, room):
    # one test per room, so a failure says whose cycle it is; a cycle across rooms shows under
    # each room it touches
    found = [(group, imps) for group, imps in import_cycles(tree)
             if any(room_of(m) == room for m in group)]
    _report(f"import cycles touching {room}",
            ["cycle " + " <-> ".join(group) + "\n    " + "\n    ".join(map(str, imps))
             for group, imps in found])


def test_acq_never_redirects_stdout(tree):
    _report("acq lines with redirect_stdout", mentions(tree, "acq", "redirect_stdout"))


# ---- the checker itself, on a synthetic tree ----------------------------------------------------

def _write(root: Path, files: dict[str, str]) -> None:
    for rel, text in files.items():
        p = root / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(text)


def test_checker_finds_what_it_must(tmp_path):
    _write(tmp_path, {
        "recon/__init__.py": "",
        "recon/a.py": "def f():\n    from . import b\n",                 # function-level, relative
        "recon/b.py": "from spdepth.recon.a import f\n",                 # cycle a <-> b
        "recon/c.py": "import numpy\nfrom acq import session\n",         # against the flow
        "drivers/__init__.py": "",
        "drivers/d.py": "import importlib\nimportlib.import_module('spdepth.gui.w')\n",
        "acq/__init__.py": "",
        "acq/session.py": "import contextlib\nwith contextlib.redirect_stdout(None): pass\n",
        "acq/lib.py": "from ..gui import w\n",                           # not the CLI
        "acq/commands/__init__.py": "from . import scan\n",              # own submodule: fine
        "acq/commands/scan.py": "from spdepth.acq import commands\nfrom spdepth.gui.w import W\n",
        "gui/__init__.py": "",
        "gui/w.py": "W = 1\ndef g():\n    from spdepth.acq.commands.scan import x  # argparse\n",
    })
    t = scan(tmp_path)
    assert set(t.modules) == {"recon", "recon.a", "recon.b", "recon.c", "drivers", "drivers.d", "acq",
                              "acq.session", "acq.lib", "acq.commands", "acq.commands.scan", "gui",
                              "gui.w"}
    assert [(i.path, i.line, i.target) for i in imports_against_the_flow(t, "recon", ("acq",))] == [
        ("recon/c.py", 2, "acq.session")]
    assert [i.target for i in imports_against_the_flow(t, "drivers", ("gui",))] == ["gui.w"]
    [cli] = gui_imports_of_the_cli(t)
    assert (cli.path, cli.line, cli.in_function) == ("gui/w.py", 3, True)
    assert sorted(i.source for i in gui_importers_outside_the_cli(t)) == ["acq.lib", "drivers.d"]
    assert mentions(t, "gui", "argparse") == [
        "gui/w.py:3: from spdepth.acq.commands.scan import x  # argparse"]
    assert [m.split(":")[0] for m in mentions(t, "acq", "redirect_stdout")] == ["acq/session.py"]
    cycles = import_cycles(t)
    # the CLI and the window importing each other is a cycle too; the package's own submodule
    # (acq.commands -> acq.commands.scan -> acq.commands) is not
    assert [group for group, _ in cycles] == [["acq.commands.scan", "gui.w"], ["recon.a", "recon.b"]]
    assert sorted((i.source, i.line, i.in_function) for i in cycles[1][1]) == [
        ("recon.a", 2, True), ("recon.b", 1, False)]


def test_checker_passes_a_clean_tree_and_finds_longer_cycles(tmp_path):
    _write(tmp_path, {
        "acq/__init__.py": "from .x import X\n",
        "acq/x.py": "from .y import Y\nX = 1\n",
        "acq/y.py": "import spdepth.recon.z\nY = 2\n",
        "recon/__init__.py": "",
        "recon/z.py": "import numpy as np\n",
    })
    t = scan(tmp_path)
    assert import_cycles(t) == []
    assert imports_against_the_flow(t, "recon", ("acq", "gui", "drivers")) == []
    _write(tmp_path, {"acq/y.py": "def f():\n    import acq.z\n",
                      "acq/z.py": "from acq.x import X\n"})
    t = scan(tmp_path)
    assert [group for group, _ in import_cycles(t)] == [["acq.x", "acq.y", "acq.z"]]

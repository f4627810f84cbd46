"""The package's shape, read from its sources (ast), not run: rooms that
import only the rooms below them, no import cycle, no module that reads
another's underscored names, every folder opening with what it holds, host
modules paired with their kernels by name, kernel includes that pyopencl's
cache can follow, and no run of code written twice."""
import ast
import re
from collections import defaultdict
from pathlib import Path

import pytest

import places

PACKAGE = places.REPO / "hlbvh_cl"
KERNELS = places.REPO / "kernels"

#: The rooms from the bottom up: a module may import its own room and those
#: before it.  The top level's modules stand between them: the Mesh (plain
#: checked arrays) on core, the Scene and its pickled spec on the queries,
#: the CLI and the package's public names above everything.
LAYERS = ["core", "mesh", "device", "parallel", "build", "query", "travel", "scene", "render",
          "io", "distributed", "cli"]
TOP_LEVEL = {"mesh": "mesh", "scene": "scene", "travel": "travel", "cli": "cli",
             "__init__": "cli", "__main__": "cli", "dask": "cli", "scenefile": "cli"}

#: Modules allowed above their room, and why.
EXCEPTIONS = {
    # a program of its own, run by the probe in a child process: it drives
    # the whole package to prove a kernel variant, and nothing imports it
    "device.probe_child",
}


def modules() -> dict[str, Path]:
    """Dotted names below hlbvh_cl (``query.rays``, ``scene``) -> files."""
    found = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        parts = path.relative_to(PACKAGE).with_suffix("").parts
        found[".".join(parts)] = path
    return found


def room(name: str) -> str:
    head = name.split(".")[0]
    return TOP_LEVEL.get(head, head) if "." not in name else head


def imports(name: str, path: Path) -> set[str]:
    """The package modules that module ``name`` imports (relative imports,
    anywhere in the file), resolved to dotted names."""
    package = name.split(".")[:-1] if not path.name == "__init__.py" else name.split(".")[:-1]
    if path.name == "__init__.py":
        package = name.split(".")[:-1] if name.endswith("__init__") else name.split(".")
    known = modules()
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.level >= 1:
            base = package[:len(package) - (node.level - 1)]
            target = base + (node.module.split(".") if node.module else [])
            candidates = [".".join(target)] if node.module else []
            candidates += [".".join(target + [alias.name]) for alias in node.names]
            for candidate in candidates:
                if candidate in known:
                    found.add(candidate)
                elif candidate + ".__init__" in known and candidate:
                    found.add(candidate + ".__init__")
    found.discard(name)
    return found


def test_rooms_import_only_the_rooms_below_them():
    wrong = []
    for name, path in modules().items():
        if name in EXCEPTIONS or room(name) not in LAYERS:
            continue
        rank = LAYERS.index(room(name))
        for imported in imports(name, path):
            if room(imported) in LAYERS and LAYERS.index(room(imported)) > rank:
                wrong.append(f"{name} ({room(name)}) imports {imported} ({room(imported)})")
    assert not wrong, "\n".join(wrong)


def test_every_module_is_in_a_room_and_the_top_level_stays_small():
    found = modules()
    assert all(room(name) in LAYERS for name in found), \
        [name for name in found if room(name) not in LAYERS]
    top = [name for name in found if "." not in name]
    assert len(top) <= 10, top


def test_no_module_imports_another_in_a_cycle():
    graph = {name: imports(name, path) for name, path in modules().items()}
    done, stack = set(), []

    def visit(module):
        assert module not in stack, \
            f"import cycle: {' -> '.join(stack[stack.index(module):])} -> {module}"
        if module in done:
            return
        stack.append(module)
        for imported in sorted(graph.get(module, ())):
            visit(imported)
        stack.pop()
        done.add(module)

    for module in sorted(graph):
        visit(module)
    assert graph["core.tree"] <= {"core.layout"}


def _defined(cls: ast.ClassDef) -> set[str]:
    """The underscored names a class defines: its methods and attributes,
    and what its methods assign to self."""
    names = set()
    for node in ast.walk(cls):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and node in cls.body:
            names.add(node.name)
        elif isinstance(node, ast.Attribute) and isinstance(node.ctx, ast.Store) and \
                isinstance(node.value, ast.Name) and node.value.id in ("self", "cls"):
            names.add(node.attr)
        elif isinstance(node, (ast.AnnAssign, ast.Assign)) and node in cls.body:
            targets = node.targets if isinstance(node, ast.Assign) else [node.target]
            names |= {t.id for t in targets if isinstance(t, ast.Name)}
    return {n for n in names if n.startswith("_") and not n.startswith("__")}


def private_reads(path: Path) -> list[str]:
    """Reads of another module's (or another class's) underscored names:
    ``from x import _name``, and ``obj._name`` outside the class that
    defines _name (self._name and cls._name are the class's own)."""
    tree = ast.parse(path.read_text())
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            found += [f"line {node.lineno}: imports {alias.name}" for alias in node.names
                      if alias.name.startswith("_") and not alias.name.startswith("__")]

    def walk(node, owner: set[str]):
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.ClassDef):
                walk(child, _defined(child))
                continue
            if isinstance(child, ast.Attribute) and child.attr.startswith("_") and \
                    not child.attr.startswith("__"):
                value = child.value
                own = isinstance(value, ast.Name) and value.id in ("self", "cls")
                if not own and child.attr not in owner:
                    found.append(f"line {child.lineno}: {ast.unparse(child)}")
            walk(child, owner)
    walk(tree, set())
    return found


@pytest.mark.parametrize("folder", ["hlbvh_cl", "tests", "bench", "examples"])
def test_no_module_reads_another_modules_underscored_names(folder):
    """Rooms meet through public names and Scene.borrow(); tests through the
    public API and their support helpers."""
    wrong = {str(path.relative_to(places.REPO)): reads
             for path in sorted((places.REPO / folder).rglob("*.py"))
             if (reads := private_reads(path))}
    assert not wrong, "\n".join(f"{path}: {'; '.join(reads)}" for path, reads in wrong.items())


def test_every_folder_opens_with_what_it_holds():
    for package in sorted(PACKAGE.rglob("__init__.py")):
        doc = ast.get_docstring(ast.parse(package.read_text()))
        assert doc and "import" in doc, f"{package} says nothing of what it holds and imports"
    for folder in sorted(p for p in KERNELS.rglob("*") if p.is_dir()) + [KERNELS]:
        readme = folder / "README.md"
        assert readme.is_file() and len(readme.read_text().split()) > 20, \
            f"{folder} has no README.md saying what it holds"


def test_each_kernel_has_its_host_module_in_the_same_room():
    """kernels/ROOM/NAME.cl is run by hlbvh_cl/ROOM/NAME.py (the rooms'
    names are the same on both sides)."""
    orphans = []
    for kernel in sorted(KERNELS.rglob("*.cl")):
        relative = kernel.relative_to(KERNELS).with_suffix("")
        host = PACKAGE.joinpath(*relative.parts).with_suffix(".py")
        if not host.is_file():
            orphans.append(f"{kernel.relative_to(KERNELS)} has no {host.relative_to(places.REPO)}")
    assert not orphans, "\n".join(orphans)


def test_kernel_includes_are_named_from_the_kernels_root():
    """pyopencl's binary cache follows an #include only through the -I
    path (the kernels' root): a name relative to the including file would
    build, and then serve a stale binary after that header changed."""
    wrong = []
    for source in sorted(KERNELS.rglob("*")):
        if source.suffix not in (".cl", ".h"):
            continue
        for number, line in enumerate(source.read_text().splitlines(), 1):
            found = re.match(r'\s*#\s*include\s+"([^"]+)"', line)
            if found and not (KERNELS / found.group(1)).is_file():
                wrong.append(f"{source.relative_to(KERNELS)}:{number}: {found.group(1)}")
    assert not wrong, "\n".join(wrong)


#: Shortest run of code lines counted as written twice.
RUN = 6


def _code_lines(path: Path) -> list[tuple[int, str]]:
    """(line number, text) of the lines that carry code: comments, blank
    lines, lone punctuation and imports left out, white space folded."""
    comment = "#" if path.suffix == ".py" else "//"
    kept, in_block = [], False
    for number, line in enumerate(path.read_text().splitlines(), 1):
        text = line.strip()
        if path.suffix != ".py":
            if in_block:
                if "*/" in text:
                    in_block, text = False, text.split("*/", 1)[1].strip()
                else:
                    continue
            if text.startswith("/*"):
                if "*/" not in text:
                    in_block = True
                    continue
                text = text.split("*/", 1)[1].strip()
        text = text.split(comment)[0].strip() if not text.startswith(("'", '"')) else text
        if not text or re.fullmatch(r"[(){}\[\],;:]+", text) or \
                text.startswith(("import ", "from ", "#include", '"""', "'''")):
            continue
        kept.append((number, " ".join(text.split())))
    return kept


@pytest.mark.parametrize("folder", ["hlbvh_cl", "kernels"])
def test_no_run_of_code_is_written_twice(folder):
    seen = defaultdict(list)
    files = [p for p in sorted((places.REPO / folder).rglob("*")) if p.suffix in (".py", ".cl", ".h")]
    for path in files:
        lines = _code_lines(path)
        for i in range(len(lines) - RUN + 1):
            window = tuple(text for _, text in lines[i:i + RUN])
            seen[window].append(f"{path.relative_to(places.REPO)}:{lines[i][0]}")
    repeats = [places_ for places_ in seen.values() if len(places_) > 1]
    assert not repeats, "\n".join(" ~ ".join(p) for p in repeats[:20])

"""The packages import one way: the model package (`dimgestor`) below the server (`streamer`) below the application
(`dimgestor_app`), no import of a package above the importer's own, no import cycle among their modules
(function-level imports count too), the model package in rooms by concern (a few modules at its top, the rest in
subpackages), and no module, script or test imports a package module's private name (shared code is public, with a
docstring; tests go through the public API)."""
import ast
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PACKAGES = ("dimgestor", "streamer", "dimgestor_app")  # lowest first: each may import those before it
TOP_MODULES_MAX = 12  # modules directly in dimgestor/ (the rest are rooms: model, streaming, frontend, export, ...)
CALLERS = ("examples", "benchmarks", "tests")  # the project's own code outside the packages


def modules(root: Path, packages=PACKAGES) -> dict[str, Path]:
    """Dotted module name -> file, for every .py under the packages (a package is its __init__.py)."""
    found = {}
    for package in packages:
        for path in sorted((root / package).rglob("*.py")):
            parts = path.relative_to(root).with_suffix("").parts
            found[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return found


def imports(path: Path, name: str) -> list[tuple[str, str | None, int]]:
    """Every import in the file, at any depth: (module imported from, name taken from it or None, line)."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    out = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            out += [(a.name, None, node.lineno) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                up = package.split(".")[:len(package.split(".")) - (node.level - 1)]
                base = ".".join(up + ([node.module] if node.module else []))
            out += [(base, a.name, node.lineno) for a in node.names]
    return out


def graph(root: Path, packages=PACKAGES) -> dict[str, set[str]]:
    """Module -> the package modules it imports (`from p import m` where m is a module is an import of p.m)."""
    mods = modules(root, packages)
    edges = {m: set() for m in mods}
    for m, path in mods.items():
        for base, name, _ in imports(path, m):
            sub = f"{base}.{name}" if name else None
            target = sub if sub in mods else base if base in mods else None
            if target is not None and target != m:
                edges[m].add(target)
    return edges


def cycles(edges: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan), each sorted."""
    index, low, stack, on, found = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in sorted(edges[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            part = []
            while not part or part[-1] != v:
                part.append(stack.pop())
                on.discard(part[-1])
            if len(part) > 1:
                found.append(sorted(part))

    for v in sorted(edges):
        if v not in index:
            visit(v)
    return found


def private_imports(root: Path, packages=PACKAGES, callers=CALLERS) -> list[str]:
    """`from m import _name` of a package module, in the packages and in the callers' files (dunders are public;
    another library's private names are that library's business)."""
    mods = modules(root, packages)
    files = [(m, p) for m, p in mods.items()]
    files += [(p.stem, p) for d in callers if (root / d).is_dir() for p in sorted((root / d).rglob("*.py"))]
    bad = []
    for m, path in files:
        for base, name, line in imports(path, m):
            if (name and name.startswith("_") and not name.startswith("__") and base != m
                    and base.split(".")[0] in packages):
                bad.append(f"{path.relative_to(root)}:{line}: from {base} import {name}")
    return bad


def upward_imports(root: Path, packages=PACKAGES) -> list[str]:
    """Imports, at any depth, of a package that comes after the importer's own in `packages` (lowest first)."""
    bad = []
    for m, path in modules(root, packages).items():
        mine = packages.index(m.split(".")[0])
        for base, _, line in imports(path, m):
            top = base.split(".")[0]
            if top in packages and packages.index(top) > mine:
                bad.append(f"{path.relative_to(root)}:{line}: {m} imports {base}")
    return sorted(set(bad))


def test_the_packages_import_only_downwards():
    assert upward_imports(REPO) == []


def rooms(edges: dict[str, set[str]], package: str = "dimgestor") -> dict[str, set[str]]:
    """The package's rooms (its subpackages, and its top-level modules together as `package`) and the rooms each
    imports from."""
    subpackages = {".".join(m.split(".")[:2]) for m in edges if m.split(".")[0] == package and m.count(".") >= 2}

    def room(m):
        first_two = ".".join(m.split(".")[:2])
        return first_two if first_two in subpackages else package
    out = {room(m): set() for m in edges if m.split(".")[0] == package}
    for m, targets in edges.items():
        if m.split(".")[0] == package:
            out[room(m)] |= {room(t) for t in targets if t.split(".")[0] == package and room(t) != room(m)}
    return out


def test_the_model_package_keeps_a_few_modules_at_its_top_and_the_rest_in_rooms_whose_arrows_point_one_way():
    top = sorted(p.name for p in (REPO / "dimgestor").glob("*.py"))
    assert len(top) <= TOP_MODULES_MAX, top
    between = rooms(graph(REPO))
    assert {"dimgestor.model", "dimgestor.streaming", "dimgestor.frontend", "dimgestor.export", "dimgestor.training",
            "dimgestor.evaluation", "dimgestor.face", "dimgestor.retarget"} <= set(between)
    assert between["dimgestor"] == set()  # the top-level modules are the floor every room stands on
    assert cycles(between) == [], between


def test_no_import_cycle_among_the_packages_modules():
    edges = graph(REPO)
    assert len(edges) > 50  # every module was found
    assert cycles(edges) == []


def test_no_module_imports_another_modules_private_name():
    assert private_imports(REPO) == []


def _package(root: Path, files: dict[str, str]) -> Path:
    for rel, text in files.items():
        (root / rel).parent.mkdir(parents=True, exist_ok=True)
        (root / rel).write_text(text)
    return root


def test_a_cycle_through_a_function_level_import_is_found(tmp_path):
    root = _package(tmp_path, {
        "pkg/__init__.py": "",
        "pkg/low.py": "def f():\n    from .high import g\n    return g\n",
        "pkg/high.py": "from . import low\n\ndef g():\n    return low\n",
        "pkg/leaf.py": "from pkg.low import f\n",
        "pkg/sub/__init__.py": "",
        "pkg/sub/deep.py": "from ..leaf import f\n",
    })
    edges = graph(root, ("pkg",))
    assert edges["pkg.leaf"] == {"pkg.low"} and edges["pkg.sub.deep"] == {"pkg.leaf"}
    assert cycles(edges) == [["pkg.high", "pkg.low"]]


def test_an_import_of_a_higher_package_is_found_at_any_depth(tmp_path):
    root = _package(tmp_path, {
        "low/__init__.py": "",
        "low/a.py": "def f():\n    import top.cli\n",
        "low/sub/__init__.py": "",
        "low/sub/b.py": "from mid import x\nfrom ..a import f\n",
        "mid/__init__.py": "from low.a import f\n",
        "mid/x.py": "from top import cli\n",
        "top/__init__.py": "",
        "top/cli.py": "import low.a\nimport mid.x\n",
    })
    assert upward_imports(root, ("low", "mid", "top")) == [
        "low/a.py:2: low.a imports top.cli", "low/sub/b.py:1: low.sub.b imports mid", "mid/x.py:1: mid.x imports top"]


def test_a_private_name_imported_across_modules_is_found(tmp_path):
    root = _package(tmp_path, {
        "pkg/__init__.py": "__version__ = '1'\n",
        "pkg/a.py": "_x = 1\n__all__ = []\n",
        "pkg/b.py": "from pkg import __version__\n\ndef f():\n    from .a import (\n        __all__,\n        _x,\n    )\n",
        "examples/demo.py": "from pkg.a import _x as x\nfrom numpy.linalg import _umath_linalg\n",
    })
    assert private_imports(root, ("pkg",), ("examples",)) == [
        "pkg/b.py:4: from pkg.a import _x", "examples/demo.py:1: from pkg.a import _x"]

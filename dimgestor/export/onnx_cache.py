"""A per-user cache of ONNX exports: `dimgestor serve --backend onnxruntime` exports a model once (minutes) and
later starts load that export (seconds).

An entry is the folder `export_onnx` writes (graphs and manifest.json; the graphs as ONNX Runtime optimizes
them, `_ort_optimized`) plus `cache.json`: the entry's key and the sha256 and size of every file. The key is
everything the graphs depend on: the entry format, the model's fingerprint (config and every weight,
`savestate.model_fingerprint`), its normalization, K, guidance, frames per call, the batch sizes, the opset, the
versions of the exporter's packages and of ONNX Runtime, and a hash of our own code the graph is traced from
(`traced_modules`). The folder's name is a hash of the key, so a change of any of them is
another entry and a new export; nothing is ever patched in place.

An entry is served only when `problem` finds nothing wrong with it: cache.json readable and holding the key
asked for (not another model's), every file present with its size and checksum (not cut short, not altered).
Anything else is logged, moved aside and exported again. Writes are atomic: the export goes into a temporary
folder beside the entry and is renamed into place complete, with cache.json written last; a lock file beside
the entry makes concurrent starts wait for one export instead of racing two.

Where (`cache_root`): --onnx-cache DIR, else $DIMGESTOR_CACHE/onnx (the dataset cache's variable), else
%LOCALAPPDATA%\\dimgestor\\onnx on Windows, $XDG_CACHE_HOME/dimgestor/onnx or ~/.cache/dimgestor/onnx elsewhere.
"""
from __future__ import annotations

import ast
import contextlib
import hashlib
import json
import os
import shutil
import sys
import tempfile
import time
from importlib import metadata
from pathlib import Path
from typing import TYPE_CHECKING, Callable, Iterator, Sequence

if TYPE_CHECKING:
    from ..streaming.checkpoint import Bundle

__all__ = ["CACHE_FILE", "cache_root", "cached_export", "export_key", "problem", "traced_modules"]

CACHE_FILE = "cache.json"  # an entry's key and file checksums, written last
FORMAT = 2  # of an entry and its cache.json (2: the graphs optimized by ONNX Runtime); in the key
# the packages whose versions change what the exporter writes or what loads it
PACKAGES = ("torch", "onnx", "onnxscript", "onnx-ir", "onnxruntime")
# modules of ours that onnx_export imports for other things than tracing (loading, the CLI, the manifest's name),
# named from the package's root
_NOT_TRACED = frozenset({"streaming.checkpoint", "cli_help", "export.onnx_stream", "export.onnx_triton"})
_ROOT = Path(__file__).resolve().parents[1]  # the dimgestor package


def cache_root(override: str | Path | None = None) -> Path:
    """Where the exports are kept (see the module's docstring)."""
    if override is not None:
        return Path(override).expanduser()
    if os.environ.get("DIMGESTOR_CACHE"):
        return Path(os.environ["DIMGESTOR_CACHE"]).expanduser() / "onnx"
    if sys.platform == "win32" and os.environ.get("LOCALAPPDATA"):
        return Path(os.environ["LOCALAPPDATA"]) / "dimgestor" / "onnx"
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "dimgestor" / "onnx"


def traced_modules() -> list[str]:
    """Our modules the graph is made from: onnx_export and what it imports from this package, followed through
    their relative imports (read from the source, nothing imported), less the ones not traced (`_NOT_TRACED`).
    Named from the package's root (`export.onnx_export`, `model.network`, `config`)."""
    seen, todo = set(), ["export.onnx_export"]
    while todo:
        name = todo.pop()
        if name in seen or name in _NOT_TRACED or not _file(name).is_file():
            continue
        seen.add(name)
        package = name.split(".")[:-1]
        for node in ast.walk(ast.parse(_file(name).read_text(encoding="utf-8"))):
            if isinstance(node, ast.ImportFrom) and node.level:
                base = package[:len(package) - (node.level - 1)]
                if node.module:
                    todo.append(".".join(base + [node.module]))
                else:  # `from . import x`: x is a module or a name of the package
                    todo += [".".join(base + [a.name]) for a in node.names]
    return sorted(seen)


def _file(name: str) -> Path:
    return _ROOT.joinpath(*name.split(".")).with_suffix(".py")


def _code_sha256() -> str:
    h = hashlib.sha256()
    for name in traced_modules():
        h.update(name.encode() + b"\0" + _file(name).read_bytes() + b"\0")
    return h.hexdigest()


def _version(package: str) -> str | None:
    try:
        return metadata.version(package)
    except metadata.PackageNotFoundError:
        return None


def export_key(bundle: Bundle, steps: int, guidance: float, frames: int = 2, batches: Sequence[int] = ()) -> dict:
    """Everything an export's graphs depend on, as JSON values (equal keys: the same graphs)."""
    import numpy as np

    from .. import __version__
    from ..streaming.savestate import model_fingerprint
    from .onnx_export import OPSET

    norm = hashlib.sha256(b"".join(np.asarray(v, np.float64).tobytes() for v in (bundle.mean, bundle.std)))
    return {"format": FORMAT, "model": model_fingerprint(bundle.model), "normalization": norm.hexdigest(),
            "steps": int(steps), "guidance": float(guidance), "frames": int(frames),
            "batches": sorted({int(b) for b in batches} - {1}),
            "opset": OPSET, "versions": {p: _version(p) for p in PACKAGES} | {"dimgestor": __version__},
            "code": _code_sha256()}


def entry_name(key: dict) -> str:
    digest = hashlib.sha256(json.dumps(key, sort_keys=True).encode()).hexdigest()
    return f"k{key['steps']}-{digest[:20]}"


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def problem(entry: Path, key: dict) -> str | None:
    """What is wrong with the cache entry `entry` for `key` (None: it may be served)."""
    if not entry.is_dir():
        return "absent"
    try:
        record = json.loads((entry / CACHE_FILE).read_text())
        if record.get("format") != FORMAT:
            return f"{CACHE_FILE} of another format"
        if record.get("key") != key:
            return f"{CACHE_FILE} is of another model or other settings"
        files = {str(name): (int(want["bytes"]), str(want["sha256"])) for name, want in record["files"].items()}
    except (OSError, ValueError, KeyError, TypeError, AttributeError) as e:
        return f"{CACHE_FILE} unreadable ({type(e).__name__})"
    if not files:
        return "no files listed"
    for name, (size, sha256) in files.items():
        path = entry / name
        if Path(name).name != name or not path.is_file():
            return f"{name} missing"
        if path.stat().st_size != size:
            return f"{name} is {path.stat().st_size} bytes, not {size}"
        if _sha256(path) != sha256:
            return f"{name} fails its checksum"
    return None


@contextlib.contextmanager
def _locked(path: Path, log: Callable[[str], None]) -> Iterator[None]:
    """An exclusive lock on the file `path` (created) while the block runs; the system releases it if the
    process dies. Without a file lock (neither fcntl nor msvcrt) the atomic rename alone keeps entries whole."""
    with open(path, "a+b") as f:
        acquire, release = _lock_calls(f)
        if not acquire(False):
            log(f"waiting for another start exporting beside {path}")
            acquire(True)
        try:
            yield
        finally:
            release()


def _lock_calls(f) -> tuple[Callable[[bool], bool], Callable[[], None]]:
    """(acquire(wait) -> held, release()) of an exclusive lock on the open file `f`."""
    try:
        import fcntl
    except ImportError:
        fcntl = None
    if fcntl is not None:
        def acquire(wait: bool) -> bool:
            try:
                fcntl.flock(f, fcntl.LOCK_EX | (0 if wait else fcntl.LOCK_NB))
                return True
            except BlockingIOError:
                return False

        return acquire, lambda: fcntl.flock(f, fcntl.LOCK_UN)
    try:
        import msvcrt
    except ImportError:
        return (lambda wait: True), (lambda: None)

    def acquire_windows(wait: bool) -> bool:
        while True:
            try:
                f.seek(0)
                msvcrt.locking(f.fileno(), msvcrt.LK_NBLCK, 1)
                return True
            except OSError:
                if not wait:
                    return False
                time.sleep(1)

    def release_windows() -> None:
        f.seek(0)
        msvcrt.locking(f.fileno(), msvcrt.LK_UNLCK, 1)

    return acquire_windows, release_windows


def _discard(entry: Path) -> None:
    """Move an entry aside (one rename: never half an entry under its name), then delete it."""
    aside = entry.with_name(f".discarded-{entry.name}-{os.getpid()}-{time.monotonic_ns()}")
    os.replace(entry, aside)
    shutil.rmtree(aside, ignore_errors=True)


def _ort_optimized(graph: Path) -> None:
    """`graph` replaced by ONNX Runtime's own optimization of it (fusions, constant folding: its extended level,
    which holds on any CPU, unlike the layout level a session adds at load). A session on the result loads in
    about a third of the time (0.2-0.5 against 1.0-1.2 s a graph of the default model): the warm start's largest
    part after Python's imports. The result runs on ONNX Runtime only (its fused ops), which is all the cache is
    for; the key holds ONNX Runtime's version."""
    import onnxruntime as ort

    opts = ort.SessionOptions()
    opts.intra_op_num_threads = opts.inter_op_num_threads = 1
    opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_EXTENDED
    optimized = graph.with_name(f".optimized-{graph.name}")  # .onnx: the format ONNX Runtime writes it in
    opts.optimized_model_filepath = str(optimized)
    ort.InferenceSession(str(graph), opts, providers=["CPUExecutionProvider"])
    os.replace(optimized, graph)


def export_minutes(steps: int, graphs: int) -> int:
    """About how long an export takes: each graph is traced and optimized with its K steps unrolled (the
    default model on a shared 2-core machine: ~30 s a graph per step, 6 minutes for K = 4 and graphs of 1, 4 and
    8 streams)."""
    return max(1, round(graphs * steps * 30 / 60))


def cached_export(bundle: Bundle, steps: int, guidance: float, frames: int = 2, batches: Sequence[int] = (),
                  root: str | Path | None = None, log: Callable[[str], None] = print) -> Path:
    """The cache entry of `bundle`'s export with these settings: reused when whole, else exported (again)."""
    from .onnx_export import MANIFEST, export_bundle

    root = cache_root(root)
    key = export_key(bundle, steps, guidance, frames, batches)
    entry = root / entry_name(key)
    if problem(entry, key) is None:
        log(f"using cached ONNX export {entry}")
        return entry
    root.mkdir(parents=True, exist_ok=True)
    with _locked(root / f"{entry.name}.lock", log):
        why = problem(entry, key)  # another start may have written it while this one waited
        if why is None:
            log(f"using cached ONNX export {entry}")
            return entry
        if why != "absent":
            log(f"the cached ONNX export {entry} is damaged ({why}): exporting it again")
            _discard(entry)
        for stale in root.glob(f".partial-{entry.name}-*"):  # a killed start's (only the lock holder writes)
            shutil.rmtree(stale, ignore_errors=True)
        graphs = 1 + len(key["batches"])
        log(f"exporting the model for ONNX Runtime (first start with this model and settings, "
            f"~{export_minutes(steps, graphs)} min) into {entry}")
        tmp = Path(tempfile.mkdtemp(dir=root, prefix=f".partial-{entry.name}-"))
        try:
            export_bundle(bundle, tmp, steps, guidance, frames, key["batches"])
            for graph in sorted(tmp.glob("*.onnx")):  # (listed first: the optimizer writes beside them)
                _ort_optimized(graph)
            files = {p.name: {"bytes": p.stat().st_size, "sha256": _sha256(p)}
                     for p in sorted(tmp.iterdir()) if p.is_file()}
            if MANIFEST not in files:
                raise RuntimeError(f"the export wrote no {MANIFEST}")
            (tmp / CACHE_FILE).write_text(json.dumps({"format": FORMAT, "key": key, "files": files,
                                                      "written": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())},
                                                     indent=1))
            os.replace(tmp, entry)  # the entry appears whole or not at all
        except OSError:
            shutil.rmtree(tmp, ignore_errors=True)
            if problem(entry, key) is not None:  # (not another start's whole entry, renamed in first)
                raise
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise
    return entry

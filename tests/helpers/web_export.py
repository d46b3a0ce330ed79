"""The embedded default model exported for the web page once per test run and shared by every test process (an
export is ~30 s of CPU; the local-page tests and the web benchmark's test serve the same one)."""

from __future__ import annotations

import fcntl
import os
import shutil
from contextlib import contextmanager
from pathlib import Path

from streamer.web import prepare_model


def shared_folder(tmp_path_factory) -> Path:
    """The run's temporary folder that every xdist worker shares (each worker's own is one level below)."""
    base = tmp_path_factory.getbasetemp()
    return base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base


@contextmanager
def _locked(path: Path):
    with open(path, "w") as f:
        fcntl.flock(f, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(f, fcntl.LOCK_UN)


def web_export(tmp_path_factory, steps: int, frames: int) -> Path:
    """`web-exports/default_k{steps}_f{frames}` in the shared folder (benchmarks/web_local.py's `--exports`
    naming), exported by the first process that asks; the others wait for it. Read-only for its users."""
    folder = shared_folder(tmp_path_factory) / "web-exports" / f"default_k{steps}_f{frames}"
    folder.parent.mkdir(exist_ok=True)
    with _locked(folder.with_name(folder.name + ".lock")):
        if not (folder / "manifest.json").exists():
            part = folder.with_name(folder.name + ".part")
            shutil.rmtree(part, ignore_errors=True)
            prepare_model(part, None, steps=steps, frames=frames)
            part.rename(folder)
    return folder


def own_copy(export: Path, folder: Path) -> Path:
    """`folder` holding the export's files as hard links (copies where links cannot be made) and its own web.json:
    a test may add files to it without touching the shared export."""
    folder.mkdir(parents=True, exist_ok=True)
    for f in export.iterdir():
        if f.is_file() and f.name not in ("web.json", "web.json.part"):
            try:
                os.link(f, folder / f.name)
            except OSError:
                shutil.copy2(f, folder / f.name)
    return prepare_model(folder, None, export=False)

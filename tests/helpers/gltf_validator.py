"""The Khronos glTF validator (npm gltf-validator, pinned in tests/node) on one .glb/.gltf/.vrm/.vrma file, under
node: its JSON report, as the reference implementation of the glTF 2.0 rules judges the file."""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import pytest

from helpers.clients import REPO

NODE = shutil.which("node")
NODE_DIR = REPO / "tests" / "node"
SCRIPT = NODE_DIR / "validate-gltf.js"
SKIP_REASON = ("node not installed (Debian: apt-get install nodejs npm)" if NODE is None else
               None if (NODE_DIR / "node_modules" / "gltf-validator").is_dir() else
               f"npm gltf-validator not installed: run `make test` or `npm ci` in {NODE_DIR}")
needs_validator = pytest.mark.skipif(SKIP_REASON is not None, reason=SKIP_REASON or "")


def validate(path: str | Path) -> dict:
    """The validator's report (`report["issues"]` holds numErrors, numWarnings and every message with its code
    and JSON pointer); external buffers and images are read from beside the file."""
    if SKIP_REASON:
        pytest.skip(SKIP_REASON)
    r = subprocess.run([NODE, str(SCRIPT), str(path)], capture_output=True, text=True, timeout=120)
    if r.returncode not in (0, 1):  # 1: the report has errors; anything else: no report
        raise RuntimeError(f"gltf-validator failed on {path} (exit {r.returncode}): {r.stderr[-2000:]}")
    return json.loads(r.stdout)


def errors(report: dict) -> list[str]:
    """The report's errors as 'CODE at POINTER: message' lines, for assertion messages."""
    return [f"{m['code']} at {m.get('pointer', '?')}: {m['message']}" for m in report["issues"]["messages"]
            if m["severity"] == 0]

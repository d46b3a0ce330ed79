"""`dimgestor serve` keeps numpy's BLAS on one thread (`streamer.server.one_blas_thread`): a served process's
products outside torch are small, and a pool of BLAS threads spins on the cores the inference thread and the event
loop need (benchmarks/README.md, "numpy's BLAS threads"). Checked in a process of its own: the setting is the
whole process's."""

import json
import os
import subprocess
import sys

from helpers.serve import REPO

SCRIPT = """
import json, sys
import numpy, scipy.signal
from threadpoolctl import threadpool_info
from streamer.options import ServeOptions
from streamer.server import build

blas = lambda: sorted({i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"})
before = blas()
build(ServeOptions(source="ws", checkpoint=sys.argv[1], ws=("127.0.0.1", 0), steps=2, status_every=0))
print(json.dumps({"before": before, "after": blas()}))
"""


def test_a_built_server_leaves_numpys_blas_one_thread(tiny_checkpoint):
    env = {k: v for k, v in os.environ.items() if k not in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS")}
    env["OPENBLAS_NUM_THREADS"] = "2"  # (a pool of two before, on any machine)
    r = subprocess.run([sys.executable, "-c", SCRIPT, str(tiny_checkpoint)], cwd=REPO, env=env, capture_output=True,
                       text=True, timeout=120)
    assert r.returncode == 0, r.stderr[-3000:]
    got = json.loads(r.stdout.strip().splitlines()[-1])
    assert got == {"before": [2], "after": [1]}, got

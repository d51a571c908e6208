"""``process --scheduler`` on a real multi-process Dask cluster: ``dask scheduler`` and two ``dask worker``
processes started as separate programs (not an in-process LocalCluster), in another working directory."""

from __future__ import annotations

import json
import subprocess
import sys
import warnings

import numpy as np
import pytest

from omnispectral.mosaic.cluster import process_cluster, worker_environment
from omnispectral.mosaic.store import PanoramaStore
from omnispectral.product.process import process


def _levels(path) -> list[np.ndarray]:
    store = PanoramaStore.open(path)
    out = [store.read(level) for level in range(len(store.shapes))]
    return out + ([store.read_quality()] if store.has_quality else [])


@pytest.mark.slow
def test_process_on_separate_scheduler_and_worker_processes_matches_the_local_run(tmp_path):
    pytest.importorskip("distributed", reason="distributed is not installed (pip install 'omnispectral[cluster]')")
    from distributed import Client

    import omnispectral
    from tests.reliability.test_fault_injection import simulate_tiny

    def worker_state(dask_worker):  # nested: sent by value (the workers cannot import tests/)
        import cv2
        from threadpoolctl import threadpool_info

        import omnispectral

        return {"package": omnispectral.__file__, "cv2_threads": cv2.getNumThreads(),
                "blas_threads": [i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"],
                "executed": dask_worker.state.executed_count,
                "malloc_trim": __import__("os").environ.get("MALLOC_TRIM_THRESHOLD_")}

    simulate_tiny(tmp_path / "s")
    local = process(tmp_path / "s", tmp_path / "local", tile=32, progress=False, report=False)
    (tmp_path / "elsewhere").mkdir()
    with process_cluster(2, 1, directory=tmp_path / "cluster") as address:
        # the command line, with paths relative to its own directory (the workers run in tmp_path/cluster)
        run = subprocess.run([sys.executable, "-m", "omnispectral.cli", "process", "../s", "-o", "../remote",
                              "--tile", "32", "--scheduler", address, "--json"], cwd=tmp_path / "elsewhere",
                             env=worker_environment({"PYTHONWARNINGS": "ignore"}), capture_output=True, text=True,
                             timeout=600)
        assert run.returncode == 0, run.stderr[-2000:]
        with warnings.catch_warnings(), Client(address, set_as_default=False) as client:
            warnings.simplefilter("ignore")  # version-mismatch notes between the client and the workers
            states = client.run(worker_state)
    remote = json.loads(run.stdout)
    assert remote["width"] == local["width"] and remote["mosaic"]["tiles"] == local["mosaic"]["tiles"] >= 8
    a, b = _levels(tmp_path / "local" / "panorama.zarr"), _levels(tmp_path / "remote" / "panorama.zarr")
    assert len(a) == len(b) >= 3
    for x, y in zip(a, b, strict=True):
        np.testing.assert_array_equal(x, y)  # bit for bit, NaN where no camera sees
    assert np.isfinite(a[0]).mean() > 0.8  # the tiny rig leaves gaps near the poles
    # two worker processes shared the tiles and pyramid chunks; each ran this checkout's code with
    # one-thread BLAS and OpenCV pools (the tasks set OpenCV's; the nanny's environment BLAS's)
    assert len(states) == 2
    assert all(s["executed"] > 0 for s in states.values())
    assert sum(s["executed"] for s in states.values()) >= remote["mosaic"]["tiles"]
    assert {s["package"] for s in states.values()} == {omnispectral.__file__}
    assert all(s["malloc_trim"] is None for s in states.values())  # glibc's default (the nanny's slows tiles)
    assert all(s["cv2_threads"] == 1 and s["blas_threads"] and set(s["blas_threads"]) == {1}
               for s in states.values())

"""A Dask cluster of separate processes on this machine: ``dask scheduler`` and ``dask worker`` commands.

The mosaic's tiles and pyramid chunks run on any Dask distributed cluster
(:func:`omnispectral.mosaic.run.run_tasks`; ``omnispectral process --scheduler ADDRESS``).  This
module starts one the way a cluster runs it — a scheduler process and worker processes (each behind
its nanny) that share nothing with the caller but the file system — for the tests, the scaling
benchmark (``benchmarks/bench_cluster.py``) and trying ``--scheduler`` on one machine.  On a real
cluster the same two commands are started by the batch system (dask-jobqueue) or by Kubernetes
(docs/cluster.md).

Workers import the same ``omnispectral`` as the caller (its source directory is put first on their
``PYTHONPATH``) and get the nanny's one-thread BLAS/OpenMP environment; the engine's
:func:`omnispectral.threads.worker_call` also sets OpenCV's pool to one thread inside them.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager, suppress
from pathlib import Path

import omnispectral
from omnispectral.errors import ConfigurationError

__all__ = ["NANNY_ENVIRON", "process_cluster", "worker_environment"]

#: Dask configuration for the nanny (as an environment variable): keep its one-thread BLAS/OpenMP variables,
#: drop its ``MALLOC_TRIM_THRESHOLD_=65536``: with it glibc returns freed memory to the system at once and
#: every tile's temporaries are page-faulted in again — the tiles took 1.9× as long (docs/cluster.md).
NANNY_ENVIRON = {"DASK_DISTRIBUTED__NANNY__PRE_SPAWN_ENVIRON": "{'MALLOC_TRIM_THRESHOLD_': None}"}


def worker_environment(extra: dict[str, str] | None = None) -> dict[str, str]:
    """The environment of the cluster's processes: this one, with this ``omnispectral`` first on ``PYTHONPATH``
    and :data:`NANNY_ENVIRON`."""
    src = str(Path(omnispectral.__file__).resolve().parents[1])
    env = {**os.environ, **NANNY_ENVIRON}
    env.pop("MALLOC_TRIM_THRESHOLD_", None)
    env["PYTHONPATH"] = os.pathsep.join([src, *[p for p in env.get("PYTHONPATH", "").split(os.pathsep) if p]])
    env.update(extra or {})
    return env


def _log_tail(path: Path, n: int = 12) -> str:
    try:
        return "\n".join(path.read_text(errors="replace").splitlines()[-n:])
    except OSError:
        return "(no log)"


@contextmanager
def process_cluster(n_workers: int = 2, threads_per_worker: int = 1, *, directory: str | Path,
                    timeout_s: float = 90.0, env: dict[str, str] | None = None) -> Iterator[str]:
    """Start ``dask scheduler`` and ``n_workers`` × ``dask worker`` as separate processes; yield the scheduler's
    address (``tcp://127.0.0.1:PORT``, a free port) once every worker has joined; stop them all on exit.

    ``directory`` holds the scheduler file, the processes' logs and the workers' scratch space; the workers
    run with it as their working directory (not the caller's).  ``env`` adds environment variables.
    """
    if n_workers < 1 or threads_per_worker < 1:
        raise ConfigurationError(f"a cluster needs ≥ 1 worker and thread, got {n_workers} × {threads_per_worker}")
    directory = Path(directory).absolute()
    directory.mkdir(parents=True, exist_ok=True)
    scheduler_file = directory / "scheduler.json"
    scheduler_file.unlink(missing_ok=True)
    environment = worker_environment(env)
    dask_cli = [sys.executable, "-m", "dask"]
    procs: list[tuple[subprocess.Popen, Path]] = []

    def start(args: list[str], name: str) -> None:
        log = directory / f"{name}.log"
        with open(log, "wb") as fh:
            procs.append((subprocess.Popen([*dask_cli, *args], cwd=directory, env=environment, stdout=fh,
                                           stderr=subprocess.STDOUT, start_new_session=True), log))

    try:
        start(["scheduler", "--host", "127.0.0.1", "--port", "0", "--no-dashboard",
               "--scheduler-file", str(scheduler_file)], "scheduler")
        deadline = time.monotonic() + timeout_s
        while not scheduler_file.is_file():
            if procs[0][0].poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(f"the Dask scheduler did not start:\n{_log_tail(procs[0][1])}")
            time.sleep(0.1)
        address = json.loads(scheduler_file.read_text())["address"]
        for i in range(n_workers):
            start(["worker", address, "--nthreads", str(threads_per_worker), "--nworkers", "1",
                   "--no-dashboard", "--name", f"worker-{i}", "--local-directory", str(directory / f"worker-{i}")],
                  f"worker-{i}")
        from distributed import Client

        with Client(address, timeout=timeout_s, set_as_default=False) as client:
            try:
                client.wait_for_workers(n_workers, timeout=max(1.0, deadline - time.monotonic()))
            except TimeoutError:
                logs = "\n".join(f"--- {log.name}\n{_log_tail(log)}" for _, log in procs[1:])
                raise RuntimeError(f"{n_workers} Dask workers did not join {address}:\n{logs}") from None
        yield address
        with Client(address, timeout=timeout_s, set_as_default=False) as client:
            client.shutdown()  # workers and scheduler close cleanly (faster than signals to the nannies)
    finally:
        _stop([proc for proc, _ in reversed(procs)])  # workers first, then the scheduler


def _stop(procs: list[subprocess.Popen]) -> None:
    """End the cluster's processes and their children (each leads its own process group): a few seconds to
    exit after the scheduler's shutdown, then SIGTERM, then SIGKILL (a worker that has closed can still take
    ~8 s to leave the interpreter)."""
    for sig, wait_s in ((None, 1.0), (signal.SIGTERM, 5.0), (signal.SIGKILL, 5.0)):
        alive = [p for p in procs if p.poll() is None]
        if not alive:
            return
        for p in alive:
            if sig is not None:
                with suppress(ProcessLookupError):
                    os.killpg(p.pid, sig)
        deadline = time.monotonic() + wait_s
        for p in alive:
            with suppress(subprocess.TimeoutExpired):
                p.wait(timeout=max(0.0, deadline - time.monotonic()))

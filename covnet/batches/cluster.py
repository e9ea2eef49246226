"""Trials on a Dask distributed cluster (``--cluster ADDRESS`` on ``covnet sweep``, ``mc`` and
``compare``): the optional extra ``covnet[cluster]`` (``dask[distributed]``).  Imported only for
``--cluster`` (and ``covnet bench cluster``): the local path never imports dask.

:class:`DaskRunner` submits each task (the config travels inside it) as one Dask task calling
the kind's module-level function, which a worker imports from its own covnet: a worker needs
covnet installed and nothing else (no shared file system; results come back to the client,
which writes them).  The same function on the same inputs gives the same numbers, so a cluster
batch equals the local one bit for bit.  Ctrl-C cancels every task not yet finished.

:class:`LocalCluster` starts a real ``dask scheduler`` and ``dask worker`` processes on
127.0.0.1 (free ports, each in its own session), for the tests and the benchmark, and stops
them by PID.
"""

from __future__ import annotations

import contextlib
import json
import os
import queue
import shutil
import signal
import subprocess
import sys
import tempfile
import time
import uuid
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

from covnet import blas_kernel
from covnet.config import scheduler_problem
from covnet.errors import ClusterLost, UsageError

try:
    import distributed
except ImportError as exc:  # pragma: no cover (the extra is installed in CI)
    raise UsageError(
        "--cluster: runs on Dask distributed, which is not installed: "
        "pip install 'covnet[cluster]' (dask[distributed])"
    ) from exc

__all__ = ["DaskRunner", "LocalCluster", "connect", "scheduler_answers"]

CONNECT_TIMEOUT_S = 15.0
POLL_S = 0.5
"""How long the batch waits for a task before it checks that the scheduler is still there."""


def scheduler_answers(address: str, timeout_s: float | None = None) -> str | None:
    """What keeps ``address`` from being a Dask scheduler covnet can use, found within
    ``timeout_s`` (None: a scheduler answered).  Beyond :func:`~covnet.config.scheduler_problem`
    (the address's form, a refused connection), it asks the peer who it is, over Dask's own
    comm layer, in its own thread and event loop, all of it bounded: a port where something
    else listens (a web server, a zenoh router: a mistyped port) accepted the connection and
    never answered Dask's handshake, and Dask's client waited for it without end.
    ``timeout_s``: :data:`CONNECT_TIMEOUT_S` by default."""
    timeout_s = CONNECT_TIMEOUT_S if timeout_s is None else timeout_s
    problem = scheduler_problem(address, timeout_s)
    if problem is not None:
        return problem
    import asyncio  # start-up: only for --cluster
    import concurrent.futures

    from distributed.comm import connect as comm_connect

    async def identity() -> Any:
        comm = await comm_connect(address, timeout=timeout_s)
        try:
            await comm.write({"op": "identity", "reply": True})
            return await comm.read()
        finally:
            comm.abort()

    def ask() -> Any:
        return asyncio.run(asyncio.wait_for(identity(), timeout_s))

    with concurrent.futures.ThreadPoolExecutor(1) as pool:  # whatever loop the caller runs
        try:
            reply = pool.submit(ask).result()
        except TimeoutError:
            return (
                f"nothing answered as a Dask scheduler within {timeout_s:g} s (is it the "
                "scheduler's port? dask scheduler prints it: Scheduler at tcp://...)"
            )
        except Exception as exc:  # the comm layer's errors: a closed or garbled connection
            return f"no Dask scheduler answered there ({type(exc).__name__}: {exc})"
    if not isinstance(reply, dict) or reply.get("type") != "Scheduler":
        what = reply.get("type") if isinstance(reply, dict) else type(reply).__name__
        return f"it answered, but not as a Dask scheduler (as {what!r})"
    return None


def connect(address: str, timeout_s: float = CONNECT_TIMEOUT_S) -> distributed.Client:
    """A client of the scheduler at ``address`` (``tcp://host:port``); an unreachable one is a
    :class:`~covnet.errors.UsageError` (at once when nothing listens there: a refused TCP
    connection is not retried for ``timeout_s`` as Dask's client would; within ``timeout_s``
    when something else listens there, :func:`scheduler_answers`)."""
    problem = scheduler_answers(address, timeout_s)
    if problem is not None:
        raise UsageError(f"--cluster {address}: {problem}")
    try:
        return distributed.Client(
            address, timeout=f"{timeout_s}s", set_as_default=False, direct_to_workers=False
        )
    except (OSError, TimeoutError, ValueError) as exc:
        raise UsageError(
            f"--cluster {address}: cannot reach a Dask scheduler there ({exc})"
        ) from None


class DaskRunner:
    """Tasks on the Dask scheduler at ``address`` (see the module docstring)."""

    def __init__(self, address: str) -> None:
        self.address = address
        self.client = connect(address)
        self._pending: list[Any] = []
        self.kernels = self._check_kernels()

    def _check_kernels(self) -> dict[str, str | None]:
        """Each worker's OpenBLAS kernel set (:mod:`covnet.blas_kernel`).  A worker whose
        kernels differ from this process's can give other last bits: said on stderr, with the
        cure (a worker started before NumPy could be pinned, without the variable)."""
        try:
            kernels: dict[str, str | None] = self.client.run(blas_kernel.kernel)
        except Exception:  # noqa: BLE001 (a check only; the tasks say what fails)
            return {}
        mine = blas_kernel.kernel()
        other = sorted({k for k in kernels.values() if k != mine}, key=str)
        if other:
            print(
                f"covnet: warning: --cluster {self.address}: workers run OpenBLAS kernels "
                f"{other}, this machine {mine!r}: results may differ in their last bits from "
                f"a local run; start the workers with OPENBLAS_CORETYPE={blas_kernel.PINNED}",
                file=sys.stderr,
            )
        return kernels

    def imap(self, fn: Callable[[Any], Any], tasks: Sequence[Any]) -> Iterator[Any]:
        return self._imap(fn, tasks)

    def _imap(self, fn: Callable[[Any], Any], tasks: Sequence[Any]) -> Iterator[Any]:
        tag = uuid.uuid4().hex[:12]
        futures = [
            self.client.submit(fn, t, key=f"covnet-{tag}-{i}", pure=False, retries=0)
            for i, t in enumerate(tasks)
        ]
        index = {f.key: i for i, f in enumerate(futures)}
        self._pending = list(futures)
        pending = {f.key: f for f in futures}
        finished: queue.SimpleQueue[Any] = queue.SimpleQueue()
        for f in futures:  # called when it finishes, fails or is cancelled
            f.add_done_callback(finished.put)
        try:
            while pending:
                if self.client.status not in ("running", "connecting"):
                    for key in sorted(pending, key=index.__getitem__):
                        yield index[key], False, self._lost(index[key])
                    return
                try:
                    fut = finished.get(timeout=POLL_S)
                except queue.Empty:
                    continue
                if pending.pop(fut.key, None) is None:
                    continue
                yield self._outcome(index[fut.key], fut)
                fut.release()
        finally:
            self._cancel()

    def _lost(self, i: int) -> ClusterLost:
        return ClusterLost(
            f"task {i}: the Dask scheduler at {self.address} went away before it finished "
            f"(the client's status: {self.client.status})"
        )

    def _outcome(self, i: int, fut: Any) -> tuple[int, bool, Any]:
        """``(i, ok, result or exception)`` of a future that is no longer pending.  Its
        result is fetched here: a scheduler that died meanwhile makes this fail, which
        :class:`distributed.as_completed` (used before) did not catch (one future then stayed
        pending for ever: the batch waited without end)."""
        if fut.status == "finished":
            try:
                return i, True, fut.result(timeout=CONNECT_TIMEOUT_S)
            except Exception as exc:  # noqa: BLE001 (the fetch failed: the cluster's side)
                if self.client.status != "running":
                    return i, False, self._lost(i)
                err = RuntimeError(f"task {i}: its result could not be fetched: {exc!r}")
                return i, False, err
        if fut.status == "error":
            raised: Any
            try:
                raised = fut.exception(timeout=CONNECT_TIMEOUT_S)
            except Exception:  # noqa: BLE001 (as above)
                raised = None
            failure = (
                raised
                if isinstance(raised, Exception)
                else RuntimeError(f"task {i} failed on the cluster: {raised!r}")
            )
            failure.add_note(f"on the Dask cluster {self.address}, task {i}")
            return i, False, failure
        if self.client.status != "running":  # cancelled as the connection went
            return i, False, self._lost(i)
        return i, False, RuntimeError(f"task {i} was cancelled on the cluster ({fut.status})")

    def _cancel(self) -> None:
        live = [f for f in self._pending if not f.done()]
        if live:
            with contextlib.suppress(Exception):
                self.client.cancel(live, force=True)
        self._pending = []

    def close(self) -> None:
        self._cancel()
        with contextlib.suppress(Exception):
            self.client.close(timeout=5)

    def describe(self) -> dict[str, Any]:
        try:
            n = len(self.client.scheduler_info(n_workers=-1)["workers"])
        except Exception:  # noqa: BLE001 (a description only)
            n = None
        return {
            "backend": "dask",
            "cluster": self.address,
            "workers": n,
            "blas_kernels": sorted({str(k) for k in self.kernels.values()}),
        }


def _dask_command() -> list[str]:
    """How to run the ``dask`` command line of this interpreter's environment."""
    exe = Path(sys.executable).with_name("dask")
    if exe.is_file():
        return [str(exe)]
    found = shutil.which("dask")
    if found:
        return [found]
    return [sys.executable, "-m", "distributed.cli.dask_spec"]  # pragma: no cover


class LocalCluster:
    """A ``dask scheduler`` and ``workers`` ``dask worker`` processes (``threads`` threads
    each, no nanny) on 127.0.0.1, free ports; ``address`` once started.  They import the covnet
    of this process (its folder first on their ``PYTHONPATH``).  A context manager: everything
    is stopped by PID (SIGTERM, then SIGKILL) on the way out."""

    def __init__(self, workers: int = 2, threads: int = 1, start_timeout_s: float = 60.0) -> None:
        self.workers = workers
        self.threads = threads
        self.start_timeout_s = start_timeout_s
        self.procs: list[subprocess.Popen[bytes]] = []
        self.address = ""
        self._tmp = tempfile.TemporaryDirectory(prefix="covnet-dask-")

    def _spawn(self, args: list[str], log: str) -> subprocess.Popen[bytes]:
        out = open(Path(self._tmp.name) / log, "wb")  # noqa: SIM115 (closed with the process)
        # the processes import this process's covnet (a machine may have another installed)
        root = str(Path(__file__).resolve().parents[2])
        path = os.pathsep.join(p for p in (root, os.environ.get("PYTHONPATH", "")) if p)
        # no statistical profiler in the workers: it samples their threads every 10 ms
        env = {
            **os.environ,
            "PYTHONPATH": path,
            "DASK_DISTRIBUTED__WORKER__PROFILE__ENABLED": "False",
        }
        proc = subprocess.Popen(
            [*_dask_command(), *args],
            stdout=out,
            stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL,
            start_new_session=True,
            env=env,
            cwd=self._tmp.name,
        )
        out.close()
        self.procs.append(proc)
        return proc

    def __enter__(self) -> LocalCluster:
        try:
            self.start()
        except BaseException:
            self.stop()
            raise
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def start(self) -> str:
        sched_file = Path(self._tmp.name) / "scheduler.json"
        self._spawn(
            [
                "scheduler",
                "--host",
                "127.0.0.1",
                "--port",
                "0",
                "--no-dashboard",
                "--scheduler-file",
                str(sched_file),
            ],
            "scheduler.log",
        )
        deadline = time.monotonic() + self.start_timeout_s
        while not sched_file.is_file():
            self._check_alive("scheduler")
            if time.monotonic() > deadline:
                raise RuntimeError(f"dask scheduler did not start:\n{self.logs()}")
            time.sleep(0.1)
        time.sleep(0.1)  # the file is written whole before the scheduler listens on
        self.address = str(json.loads(sched_file.read_text())["address"])
        for w in range(self.workers):
            self._spawn(
                [
                    "worker",
                    self.address,
                    "--host",
                    "127.0.0.1",
                    "--nthreads",
                    str(self.threads),
                    "--no-nanny",
                    "--no-dashboard",
                    "--name",
                    f"covnet-{w}",
                    "--local-directory",
                    self._tmp.name,
                ],
                f"worker-{w}.log",
            )
        client = connect(self.address, timeout_s=self.start_timeout_s)
        try:
            client.wait_for_workers(self.workers, timeout=self.start_timeout_s)
        finally:
            client.close()
        return self.address

    def _check_alive(self, what: str) -> None:
        for p in self.procs:
            if p.poll() is not None:
                raise RuntimeError(f"{what}: a dask process ended ({p.returncode}):\n{self.logs()}")

    def logs(self) -> str:
        return "\n".join(
            f"--- {f.name}\n{f.read_text(errors='replace')[-4000:]}"
            for f in sorted(Path(self._tmp.name).glob("*.log"))
        )

    @property
    def pids(self) -> list[int]:
        return [p.pid for p in self.procs]

    def stop(self) -> None:
        """Every process by PID: the workers first, then the scheduler (SIGTERM, SIGKILL
        after 10 s each group), each reaped."""
        workers, scheduler = self.procs[1:], self.procs[:1]
        for group in (workers, scheduler):
            for p in group:
                if p.poll() is None:
                    with contextlib.suppress(ProcessLookupError):
                        p.send_signal(signal.SIGTERM)
            deadline = time.monotonic() + 10.0
            for p in group:
                try:
                    p.wait(max(0.1, deadline - time.monotonic()))
                except subprocess.TimeoutExpired:
                    with contextlib.suppress(ProcessLookupError):
                        p.kill()
                    p.wait()
        self.procs = []
        with contextlib.suppress(OSError):
            self._tmp.cleanup()

"""Running a sweep's samples on Dask: a ``LocalCluster`` of worker processes (nothing to start)
or the workers of an existing scheduler (``--scheduler tcp://HOST:8786``).

Samples go to the workers in batches; each finished batch becomes one part file, written by
this process (workers need no shared file system). The batch size comes from measurements: the
first round runs one sample per worker, which gives a first estimate of a sample's cost ``c``
(high: a worker's first sample builds the set-ups the later ones reuse), then ``c`` is the
median of the samples finished so far; a no-op task's round trip plus one part file's write
gives the overhead ``o`` of a batch. A batch of ``n`` samples
costs ``o + n c``, so ``n >= o / (0.05 c)`` keeps scheduling under 5 % of the work; a batch
also holds at least :data:`MIN_BATCH_S` of work (fewer, larger part files for a long sweep) and
at most an even share of what is left (every worker busy to the end).

Each worker process binds the C kernels once (``warm``, then the library's own per-process
cache) and keeps the spec, which is sent once (``scatter``).
"""

from __future__ import annotations

import contextlib
import functools
import gc
import logging
import math
import statistics
import sys
import time
from collections import deque
from collections.abc import Callable
from pathlib import Path

from tqdm import tqdm

from ..errors import CochleaError, printable
from . import results, sampling
from .spec import Spec

#: Scheduling (task round trip plus writing the part file) at most this fraction of the work.
OVERHEAD_FRACTION = 0.05
#: Work a batch holds at least (s of one worker), unless that leaves a worker idle at the end.
MIN_BATCH_S = 2.0
#: Batches in flight per worker: the next one is queued while one runs.
IN_FLIGHT = 2
#: The batch size follows the median cost of the last this many samples.
MEASURED_SAMPLES = 1000
#: Seconds to wait for a scheduler given by address, and for its first worker.
CONNECT_TIMEOUT_S = 30


def run_batch(spec: Spec, indices: list[int],
              evaluate: Callable[[dict], dict]) -> list[dict]:
    """One batch, on a worker: each sample's scenario built, run and measured. ``evaluate``
    gets the sample's scenario as data (:func:`~cochlea.sweep.sampling.scenario_data`): what
    its replay file (:func:`~cochlea.sweep.sampling.scenario_text`) reads as, without the
    text written and parsed again. Where ``evaluate`` has a ``many`` (a function of the list
    of samples' data giving each row and the seconds of its own work:
    ``cochlea_sweep.evaluate_many``, through a functools.partial's keywords too), the batch's
    samples go to it together, which takes them through each phase in groups; each row is the
    same. A sample's ``wall_s`` is its own work's time either way."""
    rows, data, heads = [], [], []
    vectors = {e.name: e.rule.size for e in spec.entries if e.vector}
    for i in indices:
        start = time.perf_counter()
        g, k = sampling.grid_point(spec, i)
        row = {"sample": i, "grid": g, "draw": k}
        values = sampling.inputs(spec, i)
        for name, value in values.items():
            # An entry whose values may be lists is a list in every row (a number is every
            # component): the same columns whichever samples a batch holds.
            if name in vectors and not isinstance(value, list):
                value = [value] * vectors[name]
            row.update(results.flatten(name, value))
        data.append(sampling.scenario_data(spec, i, values))
        heads.append((row, time.perf_counter() - start))
    many = _many(evaluate)
    if many is None:  # one sample after the other
        measured = []
        for d in data:
            start = time.perf_counter()
            measured.append((evaluate(d), time.perf_counter() - start))
    else:  # the phases of several samples together (cochlea_sweep.evaluate_many)
        measured = many(data)
    for (row, head_s), (values, own_s) in zip(heads, measured, strict=True):
        row.update(values)
        row["wall_s"] = head_s + own_s  # the sample's own work, wherever its phases ran
        rows.append(row)
    return rows


def _many(evaluate) -> Callable[[list], list[tuple[dict, float]]] | None:
    """``evaluate``'s way to take a batch's samples together, ``evaluate.many`` (with a
    functools.partial's arguments), or None."""
    func = getattr(evaluate, "func", evaluate)
    many = getattr(func, "many", None)
    if many is None or getattr(evaluate, "args", ()):  # a partial binding the sample: as is
        return None
    keywords = getattr(evaluate, "keywords", {})
    return functools.partial(many, **keywords) if keywords else many


def batch_rows(future, out: Path) -> list[dict]:
    """A finished batch's rows; a batch that raised on its worker is one line
    (:class:`~cochlea.sweep.results.SampleFailed`)."""
    try:
        return future.result()
    except CochleaError as exc:
        raise results.SampleFailed(f"a sample was refused on a worker ({exc}); the finished "
                                   f"batches are kept in {out}") from None
    except Exception as exc:  # noqa: BLE001 (whatever a worker raised: one line, not a trace)
        text = str(exc).splitlines()[0] if str(exc) else ""
        raise results.SampleFailed(f"a sample failed on a worker ({type(exc).__name__}: "
                                   f"{text[:300]}); the finished batches are kept in {out}: "
                                   "run the same command to resume") from None


def _noop() -> None:
    return None


def batch_size(cost_s: float, overhead_s: float, remaining: int, workers: int) -> int:
    """Samples per batch (see the module's docstring); ``cost_s``: one sample's run."""
    cost_s = max(cost_s, 1e-6)
    n = max(math.ceil(overhead_s / (OVERHEAD_FRACTION * cost_s)), math.ceil(MIN_BATCH_S / cost_s))
    share = max(1, math.ceil(remaining / (IN_FLIGHT * workers)))
    return max(1, min(n, share))


#: The loggers whose records :func:`one_line_logs` folds: Dask's, and tornado's beneath it.
DASK_LOGGERS = ("distributed", "tornado")


class _OneLineErrors(logging.Filter):
    """A Dask log record on one line, without a traceback. Dask logs a broken connection with
    its traceback: when the sweep is interrupted (Ctrl-C, SIGTERM, a hang-up sent to the whole
    process group) its workers go first, and the scheduler's or a worker's write to them then
    printed a traceback of distributed's internals beside "cochlea-sweep: interrupted", as if
    the sweep had crashed; such a record's exception is folded into its line (its type and
    text). And a worker logs a task that raised as several lines, the last a ``Traceback:``
    (``distributed.worker - ERROR - Compute Failed``, beside the sweep's own line saying which
    sample failed and why): every multi-line message is one line, its lines joined by "; ",
    a traceback's left out. Other loggers' records pass as they are."""

    def filter(self, record: logging.LogRecord) -> bool:
        if record.name.split(".")[0] not in DASK_LOGGERS:
            return True
        text = record.getMessage()
        if record.exc_info and record.exc_info[1] is not None:
            exc = record.exc_info[1]
            text = f"{text} ({type(exc).__name__}: {exc})"
        if "\n" in text or "\r" in text:
            text = "; ".join(" ".join(line.split()) for line in text.splitlines()
                             if line.strip() and not line.lstrip().startswith("Traceback"))
        record.msg, record.args = text, None
        record.exc_info = record.exc_text = record.stack_info = None
        return True


def one_line_logs() -> None:
    """Every handler that prints Dask's records (distributed's own, or wherever they propagate
    to) prints them on one line, without a traceback (:class:`_OneLineErrors`); in this
    process, and in a local cluster's workers through ``client.run``. Idempotent."""
    for name in DASK_LOGGERS:
        logger: logging.Logger | None = logging.getLogger(name)
        while logger is not None:
            for handler in logger.handlers:
                if not any(isinstance(f, _OneLineErrors) for f in handler.filters):
                    handler.addFilter(_OneLineErrors())
            logger = logger.parent if logger.propagate else None


#: Schemes a scheduler may be reached by only with certificates, which the commands do not
#: take: Dask's client raised TypeError for them.
_SECURE_SCHEMES = ("tls", "wss")


def _connectable(scheduler: str) -> None:
    """Refuse a scheduler address Dask cannot connect to at all, before a Client is made: an
    unknown scheme, a backend that is not installed (``ucx://`` without UCX: a TypeError of an
    abstract class), a scheme that needs certificates (``tls://``, ``wss://``)."""
    from distributed.comm import parse_address  # noqa: PLC0415 (see connect)
    from distributed.comm.registry import get_backend  # noqa: PLC0415

    scheme, _ = parse_address(scheduler)
    get_backend(scheme).get_connector()
    if scheme in _SECURE_SCHEMES:
        raise ValueError(f"{scheme}:// needs TLS certificates, which cochlea-sweep and "
                         "cochlea-tune do not take: give the scheduler's tcp:// address")


def connect(workers: int | None, scheduler: str | None):
    # distributed is imported here: it takes a second, which the spec's checks and the
    # subcommands (replay, report) need not wait for.
    from distributed import Client, LocalCluster  # noqa: PLC0415

    if scheduler is not None:
        client = None
        try:
            _connectable(scheduler)  # before a Client is made: see there
            client = Client(scheduler, timeout=CONNECT_TIMEOUT_S)
            client.wait_for_workers(1, timeout=CONNECT_TIMEOUT_S)
        except Exception as exc:  # noqa: BLE001 (any failure to connect is one line)
            # Not only OSError, TimeoutError, ValueError: tls:// without a certificate raised
            # TypeError, ucx:// without UCX a TypeError of an abstract class.
            if client is not None:
                with contextlib.suppress(Exception):
                    client.close()
            # A Client whose construction raised is half made, its loop thread started: its
            # __del__ closes it now, not when a later collection happens to run it while
            # another Client starts (a deadlock on distributed's loop lock, seen in-process).
            gc.collect()
            text = (str(exc).strip().splitlines() or [""])[0]
            raise CochleaError(f"--scheduler {printable(scheduler)}: cannot reach a Dask "
                               f"scheduler with workers there ({type(exc).__name__}: "
                               f"{printable(text)[:300]}); start `dask scheduler` and `dask "
                               f"worker {printable(scheduler)}` (a tcp:// address: no TLS), "
                               "or leave --scheduler out for local workers") from None
        return client, None
    # No dashboard; the scheduler's HTTP routes (health, metrics) on a port the system
    # chooses: on distributed's default, 8787, a second sweep or tune on the machine (or
    # anything else there) got the port taken and printed a UserWarning into its stderr.
    cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                           dashboard_address=None, silence_logs=logging.ERROR,
                           scheduler_kwargs={"dashboard_address": ":0"})
    one_line_logs()  # the scheduler and the nannies run in this process
    client = Client(cluster)
    try:
        client.run(one_line_logs)  # the workers' processes (ours: a remote cluster's are not)
    except BaseException:  # an interrupt already: nothing of the cluster is left running
        client.close()
        cluster.close()
        raise
    return client, cluster


def run(spec: Spec, out: Path, evaluate: Callable[[dict], dict], *, workers: int | None = None,
        scheduler: str | None = None, batch: int | None = None, progress: bool = True,
        warm: Callable[[], object] | None = None, log=None) -> dict:
    """Run every sample not yet in ``out``; returns what ran (``samples``, ``batches``,
    ``batch``, ``workers``, ``overhead_s``, ``wall_s``). An interrupt (KeyboardInterrupt) leaves
    every finished batch in ``out``."""
    resuming = results.check(out, spec)  # before any worker starts; nothing written yet
    lock, created = None, []
    if resuming:  # another run's folder in use is refused here, before anything changes
        lock = results.hold(out)
    try:
        missing = deque(sorted(set(range(spec.total)) - (results.done(out, spec.total) if resuming
                                                         else set())))
    except BaseException:
        results.release(lock)
        raise
    info = {"samples": len(missing), "batches": 0, "batch": batch, "workers": 0,
            "overhead_s": None, "wall_s": 0.0}
    if not missing:
        results.release(lock)
        return info
    start = time.perf_counter()
    try:
        client, cluster = connect(workers, scheduler)
    except BaseException:
        results.release(lock)
        raise
    bar = None
    try:
        if lock is None:
            lock, created = results.claim(out)  # the lock first: then the folder is written
        results.prepare(out, spec)
        # Whatever another run finished while this one started (it held the lock then).
        missing = deque(sorted(set(range(spec.total)) - results.done(out, spec.total)))
        n_workers = len(client.scheduler_info()["workers"])
        info["workers"] = n_workers
        if warm is not None:
            client.run(warm)
        remote_spec = client.scatter(spec, broadcast=True)
        trips = []
        for _ in range(5):
            t0 = time.perf_counter()
            client.submit(_noop, pure=False).result()
            trips.append(time.perf_counter() - t0)
        overhead = statistics.median(trips)
        if log:
            log(f"{len(missing)} of {spec.total} samples to run on {n_workers} worker(s)")
        bar = tqdm(total=spec.total, initial=spec.total - len(missing), unit="sample",
                   file=sys.stderr, disable=not progress, smoothing=0.05, dynamic_ncols=True)
        size = batch
        costs: deque[float] = deque(maxlen=MEASURED_SAMPLES)  # the last samples' runs (s)

        def submit(n: int):
            take = [missing.popleft() for _ in range(min(n, len(missing)))]
            return client.submit(run_batch, remote_spec, take, evaluate, pure=False)

        from distributed import as_completed  # noqa: PLC0415 (see connect)

        # The first round measures: one sample per worker (unless --batch says otherwise).
        pending = as_completed([submit(size or 1) for _ in range(n_workers) if missing])
        in_flight = pending.count()
        for future in pending:
            rows = batch_rows(future, out)
            t0 = time.perf_counter()
            try:
                results.write_part(out, rows)
            except results.WriteFailed as exc:
                raise results.WriteFailed(f"{exc}; every finished batch is kept in {out}: "
                                          "free some space and run the same command to "
                                          "resume") from None
            created = []  # a batch is written: the folder is the sweep's now
            write_s = time.perf_counter() - t0
            info["batches"] += 1
            in_flight -= 1
            bar.update(len(rows))
            costs.extend(r["wall_s"] for r in rows)
            if batch is None:
                # Measured again after every batch: a worker's first sample also builds the
                # set-ups its later samples reuse (cochlea.sim.setup.unit_setups), so the first
                # round overstates a sample's cost, by ten times for the thesis studies.
                cost = statistics.median(costs)
                info["overhead_s"] = overhead + write_s
                size = batch_size(cost, overhead + write_s, len(missing), n_workers)
                info["batch"] = max(info["batch"] or 0, size)
            while missing and in_flight < IN_FLIGHT * n_workers:
                share = max(1, math.ceil(len(missing) / (IN_FLIGHT * n_workers)))
                pending.add(submit(min(size, share)))
                in_flight += 1
    except BaseException:
        # A new folder that got no sample (refused, interrupted, a write failed) is removed.
        results.discard(out, created)
        raise
    finally:
        if bar is not None:
            bar.close()
        client.close()
        if cluster is not None:
            cluster.close()
        results.release(lock)
    info["wall_s"] = time.perf_counter() - start
    return info

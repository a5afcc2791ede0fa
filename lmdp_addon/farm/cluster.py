"""A bake farm: a Dask distributed client, connected to a scheduler or to a local cluster, whose
workers have been checked to run the same engine.

Dask is imported here (and in :mod:`~lmdp_addon.farm.units`) only, when a farm is made; the rest
of the engine needs numpy, scipy and embreex alone. A worker on another machine is a plain
Python process with those and this package importable::

    PYTHONPATH=/path/to/checkout dask worker tcp://scheduler:8786 --nworkers N --nthreads 1

(N: the machine's cores; one unit per process keeps its memory bounded, about 64 MiB a unit).
The scheduler (``dask scheduler``) needs no engine: the tasks it sees are sent by value and
their inputs are bytes (``units``).
"""
from . import aliases, units, versions
from .versions import FarmError

#: The pinned release (requirements-dev.txt); what the message for a missing dask asks for.
DASK_PIN = "2026.8.0"
#: Seconds to wait for a scheduler before refusing it.
CONNECT_TIMEOUT = 5.0


def import_distributed():
    """The ``distributed`` module, or :class:`FarmError` saying how to install it."""
    try:
        import distributed
    except ImportError as error:
        raise FarmError(f"bake farms need Dask distributed ({error}): "
                        f"pip install 'dask[distributed]=={DASK_PIN}'") from error
    return distributed


def unreachable_message(address, timeout, error):
    return (f"cannot reach the Dask scheduler at {address} within {float(timeout):g} s ({error}): start "
            "it with `dask scheduler` on that machine, or check the address and port")


def check_reachable(address, timeout):
    """Raise ``ValueError`` if ``address`` is not a scheduler address, ``OSError`` if nothing
    accepts a TCP connection there within ``timeout`` seconds (tcp:// and tls:// addresses)."""
    import socket
    from distributed.comm.addressing import parse_address, parse_host_port
    from distributed.comm.registry import get_backend
    scheme, location = parse_address(address)
    get_backend(scheme)                     # ValueError: unknown scheme
    if scheme in ("tcp", "tls"):
        host, port = parse_host_port(location)
        with socket.create_connection((host, int(port)), timeout=float(timeout)):
            pass


def local_workers_import_the_engine():
    """Let local worker processes (spawned with this process's ``sys.path``) import the engine as
    ``lmdp_addon``: inside Blender it is the extension's copy, under another package name, so its
    folder's parent goes at the end of ``sys.path`` (the extension's modules stay first)."""
    import os
    import sys
    root = os.path.dirname(versions.ENGINE_DIR)
    if aliases.engine_name() != aliases.WORKER_NAME and root not in sys.path:
        sys.path.append(root)


def _probe_function():
    """The workers' version probe, defined here so that cloudpickle sends it by value: a worker
    that cannot import the engine then still answers (with what it could not import)."""
    def probe():
        try:
            from lmdp_addon.farm import versions as worker_versions
        except Exception as error:  # the engine package is not importable on the worker
            return {"engine": f"missing ({type(error).__name__}: {error})"}
        return worker_versions.probe()
    return probe


class Farm:
    """A Dask client whose workers run this engine; a context manager (closes what it opened).

    scheduler  address of a running scheduler (``tcp://host:8786``), or None with ``workers``
    workers    start a ``LocalCluster`` of this many worker processes (1 thread each) instead
    timeout    seconds to wait for the scheduler (:data:`CONNECT_TIMEOUT`)

    A local cluster's worker processes are spawned (multiprocessing), which re-imports the main
    script in each: keep a script's work under ``if __name__ == "__main__":``.

    On connect every worker runs :func:`versions.probe`; a worker with another engine version or
    other dependency versions, or missing one, is refused (:class:`FarmError` naming its address
    and both versions). A worker that joins later checks itself on its first unit of a bake or
    build (``versions.check_engine``: the bake then fails with :class:`versions.EngineMismatch`).
    ``traffic`` counts the bytes sent (``units.Traffic``).
    """

    def __init__(self, scheduler=None, workers=None, timeout=CONNECT_TIMEOUT):
        distributed = import_distributed()
        self.cluster = None
        self.engine = None                  #: this engine's versions.probe(), once checked
        self.traffic = units.Traffic()
        if (scheduler is None) == (workers is None):
            raise FarmError("give a farm either a scheduler address (e.g. tcp://host:8786) or a number "
                            "of local worker processes, not both or neither")
        if scheduler is None:
            n = int(workers)
            if n < 1:
                raise FarmError(f"a local farm needs at least 1 worker process (got {workers})")
            local_workers_import_the_engine()
            try:
                self.cluster = distributed.LocalCluster(n_workers=n, threads_per_worker=1, processes=True,
                                                        dashboard_address=None, silence_logs=40)
            except RuntimeError as error:   # a worker process did not start
                what = f"{n} local worker process{'es' if n > 1 else ''}"
                raise FarmError(f"the {what} did not start ({str(error).rstrip('.')}; the reason is "
                                "logged above): they re-import the main script, so a script that starts "
                                "a local farm keeps its work under `if __name__ == \"__main__\":` and does "
                                "not import bpy at its top") from error
            address = self.cluster.scheduler_address
        else:
            address = str(scheduler)
        self.address = address
        try:
            if self.cluster is None:        # refused before a Client exists (nothing left behind)
                check_reachable(address, timeout)
            self.client = distributed.Client(address, timeout=f"{float(timeout)}s", set_as_default=False)
        except ValueError as error:         # not an address: no scheme, no port, unknown scheme
            self._close_cluster()
            raise FarmError(f"{address!r} is not a Dask scheduler address ({error}): give it as "
                            "tcp://host:port, e.g. tcp://192.168.1.10:8786") from error
        except (OSError, TimeoutError) as error:
            self._close_cluster()
            raise FarmError(unreachable_message(address, timeout, error)) from error
        try:
            if self.cluster is not None:
                self.client.wait_for_workers(int(workers), timeout=60)
            self.check_workers()
            aliases.install(self.client)
        except BaseException:
            self.close()
            raise

    # ---- workers --------------------------------------------------------------------------------

    @property
    def n_workers(self):
        """Workers connected now."""
        return len(self.client.scheduler_info(n_workers=-1)["workers"])

    def check_workers(self):
        """Refuse (:class:`FarmError`) unless every worker reports this engine's
        :func:`versions.probe`; returns ``{worker address: probe}``."""
        local = versions.probe()
        reports = self.client.run(_probe_function())
        if not reports:
            raise FarmError(f"the Dask scheduler at {self.address} has no workers: start one with "
                            "`PYTHONPATH=/path/to/checkout dask worker "
                            f"{self.address} --nthreads 1`")
        for address, remote in sorted(reports.items()):
            wrong = versions.mismatches(local, remote)
            if wrong:
                raise FarmError(versions.mismatch_message(address, wrong))
        self.engine = local
        return reports

    # ---- the engine's seams (driver.bake, dynamics.build_passive_dynamics) ----------------------

    def bake_units(self, scene, settings, lmdp, portals=None):
        """A runner of one bake's work units (``units.BakeUnits``, a context manager); ``portals``:
        the world portals the bake's tracer follows (``bake.portals.Portals``, or None)."""
        return units.BakeUnits(self, scene, settings, lmdp, portals)

    def build_batches(self, scene, states, rays_per_stratum, seed, exact_nearest, light_samples,
                      points_per_batch):
        """A runner of one build's ray batches (``units.BuildBatches``, a context manager)."""
        return units.BuildBatches(self, scene, states, rays_per_stratum, seed, exact_nearest, light_samples,
                                  points_per_batch)

    # ---- lifetime -------------------------------------------------------------------------------

    def _close_cluster(self):
        if self.cluster is not None:
            self.cluster.close()
            self.cluster = None

    def close(self):
        """Close the client and the local cluster, if this farm started one."""
        client = getattr(self, "client", None)
        if client is not None:
            client.close()
            self.client = None
        self._close_cluster()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False

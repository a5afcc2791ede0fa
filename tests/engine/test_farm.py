"""Bake farms on Dask distributed (lmdp_addon.farm): a LocalCluster of 2 worker processes (1
thread each) on this machine must give bakes and builds byte-identical to the local ones, also
when a worker is killed mid-bake, and refuse what it cannot use (an unreachable scheduler, a
worker with another engine version or a missing dependency, no dask)."""
import contextlib
import os
import re
import signal
import sys
import time

import numpy as np
import pytest

from lmdp_addon.bake import driver
from lmdp_addon.errors import Cancelled
from lmdp_addon.model import dynamics as dynamics_module
from lmdp_addon.model import pipeline
from lmdp_addon.progress import Progress
from lmdp_addon.settings import Settings

from lmdp_addon import farm as farm_api
from lmdp_addon.farm.cluster import FarmError, import_distributed
from lmdp_addon.farm.versions import EngineMismatch

NAMES = ["Floor", "TallBox", "LeftWall"]


def small(**kw):
    base = dict(point_count=384, bake_mode="FINAL_GATHER", bake_resolution=24, bake_samples=8, bake_margin=2,
                seed=7)
    base.update(kw)
    return Settings(**base)


@pytest.fixture(scope="module")
def farm():
    with farm_api.Farm(workers=2) as made:
        yield made


@pytest.fixture(scope="module")
def solved(cornell):
    return pipeline.run_all(cornell, small())


@pytest.fixture
def many_units(monkeypatch):
    """Small work units (the client cuts them: the workers only get their numbers)."""
    monkeypatch.setattr(driver, "PATHS_PER_UNIT", 512)


def assert_same_bake(local, remote):
    assert [o.name for o in local.objects] == [o.name for o in remote.objects]
    for a, b in zip(local.objects, remote.objects):
        assert np.array_equal(a.image, b.image), a.name
        assert np.array_equal(a.standard_error, b.standard_error, equal_nan=True), a.name
        assert a.stats.total_rays == b.stats.total_rays


def assert_same_matrix(a, b):
    assert a.shape == b.shape
    for part in ("data", "indices", "indptr"):
        assert np.array_equal(getattr(a, part), getattr(b, part)), part


@pytest.mark.parametrize("mode", ["UNGUIDED", "GUIDED", "FINAL_GATHER", "RESIDUAL"])
def test_farm_bake_is_byte_identical_to_the_local_bake(cornell, solved, farm, many_units, mode):
    settings = small(bake_mode=mode)
    local = driver.bake(cornell, NAMES, settings, lmdp=solved)
    before = farm.traffic.units
    remote = farm_api.bake(cornell, NAMES, settings, lmdp=solved, farm=farm)
    assert farm.traffic.units - before >= 3 * 4      # the units really ran on the farm
    assert_same_bake(local, remote)


def test_an_auto_farm_bake_is_byte_identical_to_the_local_bake(cornell, solved, farm, many_units, monkeypatch):
    """AUTO on the farm (its guided bake forced: every pilot counts as noisy): the pilots run
    locally, the bake on the workers, with the guide the local bake makes (sized for the bake)."""
    from lmdp_addon.bake import auto
    monkeypatch.setattr(auto, "NOISY", 0.0)
    monkeypatch.setattr(auto, "GUIDED_RAY_COST", 1e-3)     # ... and GUIDED always the more efficient
    settings = small(bake_mode="AUTO", bake_samples=128)   # the guide: G = 8 for 128 samples
    local = driver.bake(cornell, ["Floor"], settings, lmdp=solved)
    assert local.auto.solved and local.auto.mode == "GUIDED" and local.guide_info["fine_resolution"] == 8
    remote = farm_api.bake(cornell, ["Floor"], settings, lmdp=solved, farm=farm)
    assert remote.auto.as_dict() == local.auto.as_dict()
    assert_same_bake(local, remote)


def test_a_clamped_farm_bake_is_byte_identical_to_the_local_bake(cornell, solved, farm, many_units):
    """The sample clamp and its roulette travel with the settings (bake/clamp.py)."""
    settings = small(bake_mode="GUIDED", bake_content="DIRECT_INDIRECT", clamp_direct=1.0, clamp_indirect=0.5,
                     min_light_bounces=1)
    local = driver.bake(cornell, NAMES, settings, lmdp=solved)
    assert sum(o.stats.clamped for o in local.objects) > 0
    assert_same_bake(local, farm_api.bake(cornell, NAMES, settings, lmdp=solved, farm=farm))


def test_a_farm_bake_under_an_hdri_draws_the_local_probes_portals(farm, many_units):
    """The world portals are learned once, by the client's probe, and sent with the recipe."""
    from test_portals import open_box_under_a_sun
    scene = open_box_under_a_sun()
    settings = small(bake_mode="UNGUIDED", bake_resolution=16)
    local = driver.bake(scene, ["Floor", "BackWall"], settings)
    assert local.portals["used"]
    remote = farm_api.bake(scene, ["Floor", "BackWall"], settings, farm=farm)
    assert remote.portals == local.portals
    assert_same_bake(local, remote)


def test_farm_build_is_byte_identical_to_the_local_build(cornell, farm, monkeypatch):
    monkeypatch.setattr(dynamics_module, "RAYS_PER_BATCH", 1 << 12)   # several batches (client side)
    settings = small()
    local = pipeline.run_all(cornell, settings)
    before = farm.traffic.units
    remote = farm_api.build(cornell, settings, farm=farm)
    assert farm.traffic.units - before >= 4
    assert_same_matrix(local.dynamics.P, remote.dynamics.P)
    assert_same_matrix(local.dynamics.stratum_transitions, remote.dynamics.stratum_transitions)
    assert local.dynamics.counts == remote.dynamics.counts
    assert np.array_equal(local.solution.z, remote.solution.z)


def test_a_worker_killed_mid_bake_changes_nothing(cornell, solved, farm, many_units):
    settings = small(bake_resolution=32)
    local = driver.bake(cornell, NAMES, settings, lmdp=solved)
    client = farm.client
    pids = client.run(os.getpid)
    killed = {}

    class KillOnce(Progress):
        def update(self, fraction, message=""):
            if not killed and "work units" in message:
                busy = {w: keys for w, keys in client.processing().items() if keys}
                victim = sorted(busy or pids)[0]
                killed[victim] = len(busy.get(victim, ()))
                os.kill(pids[victim], signal.SIGKILL)
            super().update(fraction, message)

    remote = driver.bake(cornell, NAMES, settings, lmdp=solved, farm=farm, progress=KillOnce())
    assert killed and list(killed.values())[0] >= 1      # it died holding units
    assert_same_bake(local, remote)
    client.wait_for_workers(2, timeout=60)               # the nanny restarts it for the next tests
    deadline = time.time() + 60
    while set(client.run(os.getpid).values()) & {pids[w] for w in killed} and time.time() < deadline:
        time.sleep(0.2)


def test_cancel_stops_the_farm_bake_and_releases_its_tasks(cornell, solved, farm, many_units):
    class CancelSoon(Progress):
        def should_cancel(self):
            return "work units" in self._last_message

        def emit(self, step, fraction, message):
            self._last_message = message

    progress = CancelSoon()
    progress._last_message = ""
    with pytest.raises(Cancelled):
        driver.bake(cornell, NAMES, small(bake_resolution=32), lmdp=solved, farm=farm, progress=progress)
    assert scheduler_tasks_drain(farm)


def scheduler_tasks_drain(farm, seconds=10):
    deadline = time.time() + seconds
    left = None
    while time.time() < deadline:
        left = farm.client.run_on_scheduler(lambda dask_scheduler: len(dask_scheduler.tasks))
        if left == 0:
            break
        time.sleep(0.1)
    return left == 0


def test_cancel_stops_the_farm_build(cornell, farm, monkeypatch):
    monkeypatch.setattr(dynamics_module, "RAYS_PER_BATCH", 1 << 10)

    class CancelAtFirstBatch(Progress):
        def update(self, fraction, message=""):
            if "points traced" in message:
                raise Cancelled("cancelled in the test")
            super().update(fraction, message)

    before = farm.traffic.units
    with pytest.raises(Cancelled):
        farm_api.build(cornell, small(), progress=CancelAtFirstBatch(), farm=farm)
    assert farm.traffic.units - before >= 8           # the batches were on the farm ...
    assert scheduler_tasks_drain(farm)                # ... and are gone


@contextlib.contextmanager
def first_worker_reports_engine(farm, version):
    """Inside the block the farm's first worker reports engine ``version`` (its
    ``versions.engine_version`` replaced, restored after); yields that worker's address."""
    client = farm.client
    worker = sorted(client.scheduler_info(n_workers=-1)["workers"])[0]

    def patch():
        from lmdp_addon.farm import versions
        versions._real_engine_version = versions.engine_version
        versions.engine_version = lambda: version

    def restore():
        from lmdp_addon.farm import versions
        versions.engine_version = versions._real_engine_version

    client.run(patch, workers=[worker])
    try:
        yield worker
    finally:
        client.run(restore, workers=[worker])


def test_a_worker_with_another_engine_version_is_refused(farm):
    with first_worker_reports_engine(farm, "0123456789ab") as worker:
        with pytest.raises(FarmError) as caught:
            farm.check_workers()
    message = str(caught.value)
    from lmdp_addon.farm.versions import engine_version
    assert worker in message and "0123456789ab" in message and engine_version() in message
    farm.check_workers()                                 # restored: accepted again


def test_a_worker_that_changes_after_the_connect_check_fails_the_bake(cornell, solved, farm, many_units):
    with first_worker_reports_engine(farm, "fedcba987654") as worker:
        with pytest.raises(EngineMismatch) as caught:    # a new recipe (seed): checked on its first unit
            farm_api.bake(cornell, NAMES, small(seed=1234), lmdp=solved, farm=farm)
    assert worker in str(caught.value) and "fedcba987654 on the worker" in str(caught.value)


def test_a_worker_missing_a_dependency_is_refused(farm):
    client = farm.client
    worker = sorted(client.scheduler_info(n_workers=-1)["workers"])[-1]

    def patch():
        from lmdp_addon.farm import versions
        versions._real_dependency_versions = versions.dependency_versions
        versions.dependency_versions = lambda: {**versions._real_dependency_versions(), "embreex": "missing"}

    def restore():
        from lmdp_addon.farm import versions
        versions.dependency_versions = versions._real_dependency_versions

    client.run(patch, workers=[worker])
    try:
        with pytest.raises(FarmError, match="embreex missing on the worker") as caught:
            farm.check_workers()
    finally:
        client.run(restore, workers=[worker])
    assert worker in str(caught.value)


def test_an_unreachable_scheduler_is_refused_quickly():
    t0 = time.perf_counter()
    with pytest.raises(FarmError, match=r"cannot reach the Dask scheduler at tcp://127\.0\.0\.1:9 within 2 s"):
        farm_api.Farm(scheduler="tcp://127.0.0.1:9", timeout=2)
    assert time.perf_counter() - t0 < 15


def test_missing_dask_says_what_to_install(monkeypatch):
    monkeypatch.setitem(sys.modules, "distributed", None)
    with pytest.raises(FarmError, match=r"pip install 'dask\[distributed\]==2026\.8\.0'"):
        import_distributed()


def test_a_local_bake_and_build_never_import_dask(tmp_path):
    """Dask is imported inside lmdp_addon/farm only, when a Farm is made."""
    import subprocess
    from pathlib import Path
    root = Path(__file__).resolve().parents[2]
    probe = (f"import sys; sys.path.insert(0, {str(root)!r})\n"
             "from lmdp_addon import demo_geometry, farm\n"
             "from lmdp_addon.bake import driver\n"
             "from lmdp_addon.model import pipeline\n"
             "from lmdp_addon.settings import Settings\n"
             "scene = demo_geometry.build_scene_arrays('CORNELL_BOX')\n"
             "s = Settings(point_count=64, bake_mode='GUIDED', bake_resolution=8, bake_samples=2)\n"
             "driver.bake(scene, ['Floor'], s, lmdp=pipeline.run_all(scene, s))\n"
             "print(sorted(n for n in sys.modules if n.split('.')[0] in ('dask', 'distributed', 'tornado')))\n")
    run = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    assert run.stdout.strip() == "[]"


@pytest.mark.parametrize("address, message", [
    ("nonsense", "'nonsense' is not a Dask scheduler address (missing port number"),
    ("http://127.0.0.1:9", "'http://127.0.0.1:9' is not a Dask scheduler address (unknown address scheme"),
])
def test_a_malformed_scheduler_address_is_refused(address, message):
    with pytest.raises(FarmError, match=re.escape(message)):
        farm_api.Farm(scheduler=address, timeout=2)


def test_a_scheduler_without_workers_is_refused():
    distributed = import_distributed()
    with distributed.LocalCluster(n_workers=0, processes=False, dashboard_address=":0") as empty:
        with pytest.raises(FarmError, match=re.escape(f"the Dask scheduler at {empty.scheduler_address} has no "
                                                      "workers: start one with `PYTHONPATH=")):
            farm_api.Farm(scheduler=empty.scheduler_address)

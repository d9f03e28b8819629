"""Chunked ensembles on Dask: the chunking changes nothing, a dead worker changes nothing."""
import os
import signal
import threading
import time

import h5py
import numpy as np
import pytest
from distributed import Client, LocalCluster

from ti_dk import load_scene, run
from ti_dk.control import ensemble

SCENE = dict(ensemble=40, t_end=0.002, output_times=[0.001, 0.002], observables={"left": "x < 0.5"})


def _same(a, b):
    assert np.array_equal(a.final_density, b.final_density)  # every member is the same realisation
    for k in ("mean", "variance", "skewness", "kurtosis"):
        np.testing.assert_allclose(getattr(a.stats, k), getattr(b.stats, k), rtol=1e-11, atol=1e-9)
    assert np.array_equal(a.stats.n_samples, b.stats.n_samples)
    np.testing.assert_allclose(a.diagnostics["mass"], b.diagnostics["mass"], rtol=1e-12)
    assert a.series.keys() == b.series.keys() and all(np.array_equal(a.series[k], b.series[k]) for k in a.series)


def test_chunks_cover_every_member_once():
    assert ensemble.chunks(10, 4) == [(0, 4), (4, 4), (8, 2)]
    assert sum(n for _, n in ensemble.chunks(12345, 77)) == 12345


@pytest.mark.parametrize("method", ["fv", "hybrid"])
def test_dask_chunks_equal_the_single_process_run_and_resume(tmp_path, method):
    scene = load_scene("void1d", method=method, **SCENE)
    whole = run(scene)
    split = ensemble.run(scene, "dask", out=tmp_path, chunk=7, workers=2, progress=False)
    assert split.chunks["chunks"] == 6
    _same(whole, split)
    with h5py.File(split.path) as f:  # the members' records side by side, as one process writes them
        assert np.array_equal(f["observables/left"][()], whole.series["left"])
    # a stopped run resumes with the chunks it lacks
    files = sorted((tmp_path / f"void1d_{method}_chunks").glob("chunk_*.h5"))
    assert len(files) == 6
    files[2].unlink()
    files[5].unlink()
    again = ensemble.run(scene, "dask", out=tmp_path, chunk=7, workers=2, progress=False, overwrite=True)
    _same(whole, again)


def test_a_killed_worker_changes_nothing(tmp_path):
    scene = load_scene("void1d", method="particle", **SCENE | {"ensemble": 48})
    whole = run(scene)
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0") as cluster:
        with Client(cluster) as c:
            pids = list(c.run(os.getpid).values())
        store = tmp_path / "void1d_particle_chunks"

        def kill_one():  # once a first chunk is done, kill a worker that is running another
            deadline = time.time() + 120
            while not (store.exists() and any(store.glob("chunk_*.h5"))) and time.time() < deadline:
                time.sleep(0.05)
            os.kill(pids[0], signal.SIGKILL)

        killer = threading.Thread(target=kill_one)
        killer.start()
        split = ensemble.run(scene, "dask", out=tmp_path, chunk=4, scheduler=cluster.scheduler_address,
                             progress=False)
        killer.join()
    _same(whole, split)
    assert split.chunks["chunks"] == 12 and split.chunks["retried"]

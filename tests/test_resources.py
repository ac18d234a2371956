"""The resources module: the memory probe, the cores and worker processes, the BLAS threads."""
import dataclasses
import os

import numpy as np
import pytest
from threadpoolctl import threadpool_info, threadpool_limits

import sfem_filters.cardiac.contours_route as contours_module
import sfem_filters.cardiac.strain_route as strain_module
import sfem_filters.cli as cli
import sfem_filters.filtering.cyclic as cyclic_module
import sfem_filters.filtering.iterated as iterated_module
import sfem_filters.filtering.laplace as laplace_module
from sfem_filters import resources
from sfem_filters.cardiac import closing
from sfem_filters.filtering import smoother as smoother_module
from sfem_filters.resources import BLAS_THREADS_ENV, blas_threads, chosen_blas_threads


def _blas() -> list:
    """num_threads of every BLAS library loaded (numpy's and scipy's OpenBLAS here)."""
    found = [p["num_threads"] for p in threadpool_info() if p["user_api"] == "blas"]
    assert found, "no BLAS library seen by threadpoolctl"
    return found


@pytest.fixture
def no_env(monkeypatch):
    monkeypatch.delenv(BLAS_THREADS_ENV, raising=False)


# --- BLAS threads ------------------------------------------------------------------------------------------------

def test_blas_threads_limits_every_blas_library_and_gives_the_threads_back(no_env):
    with threadpool_limits(limits=2, user_api="blas"):
        before = _blas()
        with blas_threads(1) as limit:
            assert _blas() == [1] * len(before)
            assert limit.threads == 1
        assert _blas() == before
        setter = blas_threads(1)                     # as a setter: until restored
        assert _blas() == [1] * len(before)
        setter.restore()
        setter.restore()                             # a second restore does nothing
        assert _blas() == before


def test_the_default_is_one_thread_and_the_environment_overrides_it(monkeypatch, no_env):
    assert chosen_blas_threads() == resources.DEFAULT_BLAS_THREADS == 1
    with blas_threads():
        assert _blas() == [1] * len(_blas())
    monkeypatch.setenv(BLAS_THREADS_ENV, " 2 ")
    assert chosen_blas_threads() == 2
    assert chosen_blas_threads(1) == 1                # the argument over the environment
    with threadpool_limits(limits=1, user_api="blas"):
        with blas_threads():
            assert _blas() == [2] * len(_blas())


def test_an_explicit_choice_holds_inside_the_entry_points(monkeypatch):
    """``with blas_threads(n)`` around a run: the run's own ``blas_threads()`` keeps n, over the
    environment variable too; leaving it, the environment's choice comes back."""
    monkeypatch.setenv(BLAS_THREADS_ENV, "2")
    with blas_threads(1):
        assert chosen_blas_threads() == 1
        with blas_threads():
            assert _blas() == [1] * len(_blas())
        with blas_threads(2):
            assert chosen_blas_threads() == 2
        assert chosen_blas_threads() == 1
    assert chosen_blas_threads() == 2
    a, b = blas_threads(1), blas_threads(3)            # setters restored out of order
    a.restore()
    assert chosen_blas_threads() == 3
    b.restore()
    assert chosen_blas_threads() == 2


@pytest.mark.parametrize("bad, error", [(0, ValueError), (-2, ValueError), (1.5, TypeError), (True, TypeError),
                                        ("2", TypeError), (np.float64(2.0), TypeError)])
def test_a_bad_number_of_threads_is_refused_by_name(bad, error, no_env):
    with pytest.raises(error, match=r"blas_threads\(n\): expected a positive integer number of BLAS threads"):
        blas_threads(bad)
    assert chosen_blas_threads(np.int64(2)) == 2


@pytest.mark.parametrize("bad", ["0", "-1", "1.5", "two", "1e3"])
def test_a_bad_environment_variable_is_refused_by_name(bad, monkeypatch):
    monkeypatch.setenv(BLAS_THREADS_ENV, bad)
    with pytest.raises(ValueError, match=f"environment variable {BLAS_THREADS_ENV}: expected a positive integer "
                                         f"number of BLAS threads, got '{bad}'"):
        blas_threads()
    monkeypatch.setenv(BLAS_THREADS_ENV, "")          # set but empty: the default
    assert chosen_blas_threads() == resources.DEFAULT_BLAS_THREADS


class _Lean:
    """A model of one restart state, for a result whose kinematic variances are missing."""
    n_restart = 1


def _lean_result():
    fields = {f.name: None for f in dataclasses.fields(laplace_module.SmootherResult)}
    return laplace_module.SmootherResult(**{**fields, "P_diag": np.full((2, 1), np.nan)})


class _Seen(Exception):
    """Raised by a stand-in at the start of an entry point's work, once the threads are seen."""


def _record(seen):
    def check(*args, **kwargs):
        seen.append(_blas())
        raise _Seen
    return check


@pytest.mark.parametrize("setting, expected", [(None, 1), ("2", 2)])
def test_the_estimators_entry_points_run_under_the_chosen_threads(setting, expected, monkeypatch):
    """IteratedSmoother.run, cyclic_estimate (CyclicEKF.run), the strain routes (dense_strain, whose one
    Kalman pass does not go through IteratedSmoother, and contour_strain), the smoother's covariance pass
    completed afterwards (filtering.laplace.with_covariance) and the command line run their
    work under blas_threads(): the default, or the environment variable; the threads come back after."""
    if setting is None:
        monkeypatch.delenv(BLAS_THREADS_ENV, raising=False)
    else:
        monkeypatch.setenv(BLAS_THREADS_ENV, setting)
    seen = []
    monkeypatch.setattr(iterated_module, "check_model", _record(seen))
    monkeypatch.setattr(cyclic_module, "check_model", _record(seen))
    monkeypatch.setattr(cli, "cmd_compare", _record(seen))
    monkeypatch.setattr(strain_module, "StrainRouteSettings", _record(seen))
    monkeypatch.setattr(contours_module, "ContourRouteSettings", _record(seen))
    monkeypatch.setattr(laplace_module, "check_observations", _record(seen))
    with threadpool_limits(limits=3 - expected, user_api="blas"):
        before = _blas()
        with pytest.raises(_Seen):
            iterated_module.IteratedSmoother().run(None, None)
        with pytest.raises(_Seen):
            cyclic_module.cyclic_estimate(None, None)
        with pytest.raises(_Seen):
            cli.main(["compare", "--seed", "0"])
        with pytest.raises(_Seen):
            strain_module.dense_strain(None, None, None)
        with pytest.raises(_Seen):
            contours_module.contour_strain(None, None, None)
        with pytest.raises(_Seen):
            laplace_module.with_covariance(_Lean(), None, _lean_result())
        assert _blas() == before
    assert [s == [expected] * len(s) for s in seen] == [True] * 6


def test_the_command_line_says_what_is_wrong_with_the_environment_variable(monkeypatch, capsys):
    monkeypatch.setenv(BLAS_THREADS_ENV, "many")
    assert cli.main(["compare", "--seed", "0"]) == 2
    err = capsys.readouterr().err
    assert f"error: environment variable {BLAS_THREADS_ENV}: expected a positive integer" in err
    assert "Traceback" not in err


# --- memory ------------------------------------------------------------------------------------------------------

def test_the_memory_probe_is_the_one_the_smoother_and_the_rounds_use():
    assert smoother_module.available_memory is resources.available_memory      # the public name kept
    assert closing.usable_cores is resources.usable_cores
    if os.path.exists("/proc/meminfo"):
        with open("/proc/meminfo") as f:
            meminfo = next(float(line.split()[1]) * 1024.0 for line in f if line.startswith("MemAvailable:"))
        assert 0 < resources.available_memory() <= 1.05 * meminfo     # never more than the machine's figure


def test_available_memory_is_capped_by_the_control_group(tmp_path, monkeypatch):
    limit, used = tmp_path / "memory.max", tmp_path / "memory.current"
    used.write_text("1000000000\n")
    monkeypatch.setattr(resources, "CGROUP_FILES", ((str(limit), str(used)),))
    limit.write_text("max\n")                                        # no limit: the machine's figure
    machine = resources.available_memory()
    limit.write_text("3000000000\n")                                 # 2 GB left in the group
    capped = resources.available_memory()
    assert capped == (2e9 if machine is None else min(machine, 2e9))
    limit.write_text("900000000\n")                                  # over its limit already: nothing left
    assert resources.available_memory() == 0.0


def test_available_memory_is_capped_by_the_address_space_limit(monkeypatch):
    """``ulimit -v`` (RLIMIT_AS) caps what the process can still allocate: its room is the limit
    less the address space in use, and no limit adds no cap."""
    resource = resources.resource
    monkeypatch.setattr(resources, "CGROUP_FILES", ())
    monkeypatch.setattr(resource, "getrlimit", lambda which: (resource.RLIM_INFINITY, resource.RLIM_INFINITY))
    assert resources._address_space_room() is None
    with open("/proc/self/status") as f:
        size = next(float(line.split()[1]) * 1024.0 for line in f if line.startswith("VmSize:"))
    cap = int(size + 3e9)                                             # about 3 GB of address space left
    monkeypatch.setattr(resource, "getrlimit", lambda which: (cap, cap))
    room = resources._address_space_room()
    assert abs(room - 3e9) < 0.1e9
    assert resources.available_memory() <= room + 1.0     # the machine's figure moves between reads
    monkeypatch.setattr(resource, "getrlimit", lambda which: (int(size / 2), int(size / 2)))
    assert resources._address_space_room() == 0.0


# --- cores and worker processes ----------------------------------------------------------------------------------

def test_usable_cores_are_those_of_the_affinity():
    assert resources.usable_cores() == len(os.sched_getaffinity(0)) >= 1


def test_the_process_pool_starts_fresh_processes_that_work():
    pool = resources.process_pool(1)
    try:
        pid = pool.submit(os.getpid).result(timeout=120)
        assert pid != os.getpid() and pool.submit(abs, -3).result(timeout=60) == 3
    finally:
        pool.shutdown(wait=True)


# --- frame threads -------------------------------------------------------------------------------------------------

def test_frame_map_keeps_the_order_and_the_errors_and_nests():
    from sfem_filters.resources import chosen_frame_threads, frame_map, frame_threads
    assert chosen_frame_threads() == 1
    with frame_threads(3):
        assert chosen_frame_threads() == 3
        assert frame_map(lambda t: t * t, range(7)) == [t * t for t in range(7)]
        with frame_threads(1):
            assert chosen_frame_threads() == 1
        assert chosen_frame_threads() == 3
        with pytest.raises(ZeroDivisionError):
            frame_map(lambda t: 1 / (t - 4), range(7))
        # the pool's own threads take their items one at a time: no nested pools
        assert frame_map(lambda t: chosen_frame_threads(), range(5)) == [3, 1, 1, 1, 1]
    assert chosen_frame_threads() == 1
    assert frame_map(str, []) == []


def test_frame_threads_hold_in_their_own_thread_only():
    import threading
    from sfem_filters.resources import chosen_frame_threads, frame_threads
    seen = []
    with frame_threads(2):
        other = threading.Thread(target=lambda: seen.append(chosen_frame_threads()))
        other.start()
        other.join()
        assert chosen_frame_threads() == 2
    assert seen == [1]


@pytest.mark.parametrize("bad, error", [(0, ValueError), (-2, ValueError), (1.5, TypeError), (True, TypeError)])
def test_frame_threads_refuses_a_bad_number_by_name(bad, error):
    from sfem_filters.resources import frame_threads
    with pytest.raises(error, match="n: expected a positive integer number of threads"):
        frame_threads(bad)


def test_a_linearisation_is_the_same_to_the_bit_on_threads():
    """Each frame's sensitivity (Eq. 33) is its own: taken on three threads (which the frames did run on), every
    M_t is the same."""
    from helpers import small_model
    from sfem_filters.resources import frame_threads
    rng = np.random.default_rng(3)
    model = small_model(rng, n_frames=9)
    z = np.tile(model.x0, (model.n_frames, 1))
    z[:, :model.dim_x] += 1e-4 * rng.standard_normal((model.n_frames, model.dim_x))
    import threading
    import sfem_filters.model as model_module
    real_map, seen = model_module.frame_map, set()

    def spied(fn, items):                     # the frames' work, with the thread each frame ran on
        def on_thread(i):
            seen.add(threading.get_ident())
            return fn(i)
        return real_map(on_thread, items)
    model_module.frame_map = spied
    try:
        one = model.linearise(z)
        assert seen == {threading.get_ident()}                  # one thread: this one
        seen.clear()
        with frame_threads(3):
            three = model.linearise(z)
    finally:
        model_module.frame_map = real_map
    assert len(seen) > 1                                        # the frames did run side by side
    assert one.M.shape[0] == model.n_frames - 1 and np.abs(one.M).max() > 0
    assert np.array_equal(one.M, three.M)

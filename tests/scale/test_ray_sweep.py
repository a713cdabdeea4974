"""Ray (the ``scale`` extra): an embedded local cluster of 2 workers, started once for this module, on
loopback. ``map_variants`` on warm actors gives what the in-process loop gives; a worker that dies is
restarted and its item retried; a sweep on Ray writes the in-process sweep's numbers, also when a worker is
SIGKILLed in the middle of a variant."""

from __future__ import annotations

import functools
import os

import pytest

from dmarionette.cli import main
from dmarionette.scale import WarmStates, WorkerLostError, default_ray_mode, map_variants
from dmarionette.sweep.table import read_rows, summary_columns
from tests.support.scale import (KillWorkerMidTask, always_die, build_counter, count_call, die_once, refuse_three,
                                 square_and_pid)
from tests.support.sweep import comparable

KEYS = ["strings.particle_count", "strings.tie_stiffness", "strings.tie_damping"]
SUMMARY = summary_columns(["head", "back", "knee_left", "knee_right", "hand_left", "hand_right"], ["main", "hand"])


pytestmark = pytest.mark.usefixtures("ray")  # the cluster (tests/conftest.py), started once for the module


def sweep(out, *extra) -> list[dict]:
    argv = ["sweep", "hanging", "--set", "strings.particle_count=6", "--set", "strings.k=200,400", "--set",
            "strings.k_d=2,4", "--duration", "1.2", "--out", str(out), "--quiet", "--no-picture", *extra]
    assert main(argv) == 0
    return sorted(read_rows(out / "sweep.csv", KEYS, SUMMARY), key=lambda r: r["variant"])


@pytest.fixture(scope="module")
def in_process(tmp_path_factory):
    return sweep(tmp_path_factory.mktemp("off"), "--ray", "off")


def test_the_local_cluster_is_on_loopback_with_two_cpus(ray):
    assert ray.get_runtime_context().gcs_address.startswith("127.0.0.1:")
    assert [n["NodeManagerAddress"] for n in ray.nodes() if n["Alive"]] == ["127.0.0.1"]
    assert ray.cluster_resources()["CPU"] == 2.0
    assert str(ray.get_runtime_context().get_node_id())  # a live connection
    assert os.environ["RAY_USAGE_STATS_ENABLED"] == "0"
    assert default_ray_mode() == "local"  # the sweep's default where the scale extra is installed


def test_map_variants_on_two_warm_workers_equals_the_in_process_loop(ray):
    items = list(range(10))
    off = map_variants(square_and_pid, items, ray="off")
    arrived = []
    on_ray = map_variants(square_and_pid, items, ray="local", on_result=lambda i, r: arrived.append(i))
    assert [r[0] for r in on_ray] == [r[0] for r in off] == [x * x for x in items]
    assert {r[1] for r in off} == {os.getpid()}
    workers = {r[1] for r in on_ray}
    assert len(workers) == 2 and os.getpid() not in workers  # two actors, each reused for five items
    assert sorted(arrived) == items
    assert ray.is_initialized()  # a cluster it did not start is left running


def test_a_worker_that_dies_is_restarted_and_its_item_retried(tmp_path):
    marker = tmp_path / "died"
    results = map_variants(functools.partial(die_once, str(marker)), list(range(6)), ray="local")
    assert [r[0] for r in results] == [x * x for x in range(6)]
    assert marker.is_file() and int(marker.read_text()) not in {r[1] for r in results}  # the dead one is gone


def test_a_worker_dying_past_its_retries_is_an_error_and_fn_errors_are_raised_as_themselves():
    with pytest.raises(WorkerLostError, match="a Ray worker died more than 1 times"):
        map_variants(always_die, [1], ray="local", retries=1)
    with pytest.raises(ValueError, match="item 3 is refused"):
        map_variants(refuse_three, list(range(5)), ray="local")


def test_warm_states_stay_built_on_their_workers_between_calls(ray):
    with WarmStates(build_counter, [1, 2, 3], ray="local") as states:
        assert states.worker_count == 2  # one per CPU, never more
        first = states.map(count_call, [10, 10, 10])
        second = states.map(count_call, [5, 6, 7])
        pids = states.pids()
    assert [r[0] for r in first] == [10, 20, 30] and [r[0] for r in second] == [5, 12, 21]
    assert [r[1] for r in second] == [2, 2, 2]  # the states built for the first call are the ones called again
    assert {r[2] for r in first + second} == set(pids) and os.getpid() not in pids
    assert first[0][2] == first[2][2] != first[1][2]  # item i on worker i % 2
    with WarmStates(build_counter, [1, 2, 3], ray="off") as here:
        assert here.map(count_call, [5, 6, 7]) == [(5, 1, os.getpid()), (12, 1, os.getpid()), (21, 1, os.getpid())]
    with WarmStates(build_counter, [1, -1], ray="local") as states, pytest.raises(ValueError, match="item -1 cannot"):
        states.map(count_call, [1, 1])  # an error in build: raised as itself
    assert ray.is_initialized()  # a cluster it did not start is left running


def test_a_sweep_on_two_ray_workers_writes_the_in_process_numbers(in_process, tmp_path):
    on_ray = sweep(tmp_path, "--ray", "local", "--workers", "2")
    assert [comparable(r) for r in on_ray] == [comparable(r) for r in in_process]
    batched = sweep(tmp_path / "batched", "--ray", "local", "--worlds-per-batch", "3")
    assert [comparable(r) for r in batched] == [comparable(r) for r in in_process]


def test_a_worker_killed_mid_sweep_is_replaced_and_the_sweep_completes(in_process, tmp_path):
    with KillWorkerMidTask() as killer:
        rows = sweep(tmp_path, "--ray", "local", "--workers", "2")
    assert killer.killed is not None  # a worker was SIGKILLed while it ran a variant
    assert [comparable(r) for r in rows] == [comparable(r) for r in in_process]

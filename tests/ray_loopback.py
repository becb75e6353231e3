"""A real Ray cluster on the loopback address for the Ray tests (eval, train, preprocess); no tests here.

`loopback_cluster` starts a head node of one CPU on 127.0.0.1; a test adds worker nodes with
`cluster.add_node(num_cpus=1, node_ip_address=LOOPBACK)` and kills one with `cluster.remove_node(node,
allow_graceful=False)`. `ray.cluster_utils.Cluster` is a developer API of Ray (Ray's own tests use it): it starts each
node's processes from this process with distinct ports, and `remove_node` kills exactly that node's processes.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pytest

TESTS_DIR = Path(__file__).parent
LOOPBACK = "127.0.0.1"
RAY_TEST_ENV = {
    # Ray rewrites a loopback address to the machine's own address before connecting (ray-project/ray#59110), so a
    # driver could not reach nodes listening on 127.0.0.1; with this flag off (its only other use: allowing
    # multi-node clusters on Windows/macOS) Ray keeps 127.0.0.1, and the whole cluster stays on the loopback.
    "RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER": "0",
    # The same authentication mode in every process of the test cluster (and its CLI drivers), whether or not a
    # ~/.ray/auth_token exists on this machine; the cluster listens on the loopback only.
    "RAY_AUTH_MODE": "disabled",
}
# A killed node is declared dead within about 5 s instead of Ray's default 30 s or so.
FAST_FAILURE_DETECTION = {"health_check_initial_delay_ms": 0, "health_check_period_ms": 1000}


@contextmanager
def loopback_cluster() -> Iterator[Any]:
    """A Ray cluster of one head node (1 CPU) on 127.0.0.1, its workers able to import the test helpers in tests/;
    skips the test when Ray is not installed."""
    ray = pytest.importorskip("ray", reason="the Ray backend needs `pip install 'drivesim[ray]'` (scripts/setup.sh)")
    import ray._private.ray_constants as ray_constants
    from ray.cluster_utils import Cluster

    with pytest.MonkeyPatch.context() as patch:
        for key, value in RAY_TEST_ENV.items():
            patch.setenv(key, value)
        # Ray workers import the test helpers (eval_fakes, ray_fakes) from tests/; nodes pass their environment on.
        patch.setenv("PYTHONPATH", os.pathsep.join(p for p in (str(TESTS_DIR), os.environ.get("PYTHONPATH")) if p))
        patch.setattr(ray_constants, "ENABLE_RAY_CLUSTER", False)  # read when called: also if ray was imported before
        head = {
            "num_cpus": 1,
            "node_ip_address": LOOPBACK,
            "include_dashboard": False,
            "_system_config": FAST_FAILURE_DETECTION,
        }
        ray_cluster = Cluster(initialize_head=True, head_node_args=head)
        try:
            yield ray_cluster
        finally:
            if ray.is_initialized():
                ray.shutdown()
            ray_cluster.shutdown()

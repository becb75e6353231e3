"""The expected throughput of work spread over N machines: the least of what the cores, the driver and the network
can do, and which of them bounds it, as the rows of a markdown table."""

from __future__ import annotations

from collections.abc import Callable, Sequence


def expected_rate(compute: float, driver_limit: float, network_limit: float) -> tuple[float, str]:
    """(the expected rate, what limits it: "compute", "the driver" or "the network"); rates in one unit."""
    expected = min(compute, driver_limit, network_limit)
    bound = "compute" if expected == compute else "the driver" if expected == driver_limit else "the network"
    return expected, bound


def node_rows(
    node_counts: Sequence[int],
    cores_per_node: int,
    rate_per_core: float,
    limits: tuple[float, float],
    number: str,
    last_cell: Callable[[float], str],
) -> list[str]:
    """One row per node count: | nodes | cores | compute bound | expected | limited by | last_cell(expected) |;
    `limits` = (the driver's, the network's) rate, `number` the rates' format spec (e.g. ".2f", ",.0f")."""
    rows = []
    for nodes in node_counts:
        compute = nodes * cores_per_node * rate_per_core
        expected, bound = expected_rate(compute, *limits)
        rows.append(
            f"| {nodes} | {nodes * cores_per_node} | {compute:{number}} | {expected:{number}} | {bound} | "
            f"{last_cell(expected)} |"
        )
    return rows

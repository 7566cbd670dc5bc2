"""Topological order and cycle detection against brute-force checks."""

from __future__ import annotations

import itertools
import random

import pytest

from runner.dag import CycleError, topological_order


def test_order_respects_every_edge_and_file_order():
    rng = random.Random(0)
    for _ in range(50):
        nodes = [f"n{i}" for i in range(8)]
        shuffled = nodes[:]
        rng.shuffle(shuffled)
        rank = {n: i for i, n in enumerate(shuffled)}
        edges = [(a, b) for a, b in itertools.combinations(nodes, 2) if rank[a] < rank[b] and rng.random() < 0.3]
        order = topological_order(nodes, edges)
        assert sorted(order) == sorted(nodes)
        assert all(order.index(a) < order.index(b) for a, b in edges)
    assert topological_order(["c", "a", "b"], []) == ["c", "a", "b"]


def test_cycle_is_named_in_file_order():
    with pytest.raises(CycleError) as info:
        topological_order(["x", "a", "b", "c"], [("x", "a"), ("c", "a"), ("a", "b"), ("b", "c")])
    assert info.value.cycle == ["a", "b", "c"]
    with pytest.raises(CycleError) as info:
        topological_order(["a"], [("a", "a")])
    assert info.value.cycle == ["a"]

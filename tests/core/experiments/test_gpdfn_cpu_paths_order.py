"""benchmarks/gpdfn_cpu_paths.py interleaves its arms so that no arm is favoured by its place."""
from __future__ import annotations

from collections import Counter

from .helpers import load_benchmark_script


def test_each_arm_runs_first_and_follows_every_other_arm_equally_often():
    arm_order = load_benchmark_script("gpdfn_cpu_paths").arm_order
    names = ["a", "b", "c", "d"]
    blocks = [arm_order(names, repeat) for repeat in range(2 * len(names))]
    assert all(sorted(block) == names for block in blocks)
    assert Counter(block[0] for block in blocks) == {name: 2 for name in names}
    # across blocks run back to back, every arm comes straight after each other arm
    sequence = [name for block in blocks for name in block]
    predecessors = {name: {before for before, after in zip(sequence, sequence[1:]) if after == name} for name in names}
    assert all(predecessors[name] == set(names) - {name} for name in names), predecessors

"""The names of an autograd graph's nodes, for tests that check which implementation (fused kernel or autograd) a
computation ran through."""

from __future__ import annotations


def node_names(root) -> set[str]:
    """Every autograd node name reachable from `root` (a tensor's `grad_fn`; None gives the empty set)."""
    seen, names, stack = set(), set(), [root]
    while stack:
        node = stack.pop()
        if node is None or node in seen:
            continue
        seen.add(node)
        names.add(node.name())
        stack += [n for n, _ in node.next_functions]
    return names

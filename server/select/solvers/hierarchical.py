"""Hierarchical selection by increments over several hierarchies (Mason & Blake 1997, Zach 2002).

Representations form trees (HLOD proxies over buildings, a terrain quadtree, tree
groups): a node stands for everything below it, and each node has its own chain of
levels, coarsest first. A selection is a *cut*: a set of nodes that together
represent every visible object exactly once.

Mason & Blake's greedy starts at the roots of every visible tree at their
coarsest level and repeatedly takes, over all hierarchies at once, the
*increment* with the best value = Δbenefit / Δcost that still fits the budget:

- raise a cut node to its next level, or
- split a cut node: replace it by its visible children at their coarsest level
  (invisible children were culled with their subtree and need no representation).

so each increment lands in the tree where it improves most. Every intermediate cut
is valid and feasible, so the solver is anytime.

Benefits, costs, values of every possible increment, the children (CSR), the
initial cut and the validity check are numpy; the increment loop itself is a heap
(``heapq``) loop in Python, one iteration per increment — increments are few
compared with objects, and the loop touches only the nodes whose increments it takes.

Over budget: if even the coarsest cut (the visible roots) costs more than the
budget, the result is still a valid cut — no visible object is ever left
unrepresented — and ``stats["over_budget"]`` is True; only increments that lower
the cost are taken then.
"""

from __future__ import annotations

import heapq
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from .candidates import NO_LIMIT, TimeLimit
from .result import Result

__all__ = ["Forest", "solve", "is_valid_cut", "coarsest_cut"]

#: Relative float slack on the budget (accumulated sums of costs drift by rounding).
_SLACK = 1e-12


@dataclass(frozen=True, eq=False)
class Forest:
    """Several hierarchies of representations as flat arrays, parents before children.

    parent  : (N,) int64 — parent node id, −1 for roots; parent id < child id
    benefit, cost : (N, K) float64 — per node, per level (coarsest first, cost rising along K)
    valid   : (N, K) bool — each node's levels are a prefix 0 .. K_i − 1 with K_i ≥ 1
    visible : (N,) bool — from hierarchical culling: a visible node's parent is visible
    """

    parent: np.ndarray
    benefit: np.ndarray
    cost: np.ndarray
    valid: np.ndarray
    visible: np.ndarray

    @property
    def n(self) -> int:
        return int(self.parent.shape[0])

    @property
    def k(self) -> int:
        return int(self.benefit.shape[1])

    @classmethod
    def of(cls, parent, benefit, cost, valid=None, visible=None) -> "Forest":
        """Checked construction: shapes, parent order, level prefixes, visibility closed upwards."""
        parent = np.asarray(parent, np.int64).reshape(-1)
        benefit = np.asarray(benefit, np.float64)
        cost = np.asarray(cost, np.float64)
        n = parent.shape[0]
        if benefit.ndim == 1:
            benefit = benefit[:, None]
        if cost.ndim == 1:
            cost = cost[:, None]
        valid = np.ones(benefit.shape, bool) if valid is None else np.asarray(valid, bool)
        if valid.ndim == 1:
            valid = valid[:, None]
        visible = np.ones(n, bool) if visible is None else np.asarray(visible, bool).reshape(-1)
        if benefit.ndim != 2 or benefit.shape[0] != n or cost.shape != benefit.shape or valid.shape != benefit.shape:
            raise ValueError(f"benefit, cost and valid must be (N, K) with N = {n}; got "
                             f"{benefit.shape}, {cost.shape}, {valid.shape}")
        if visible.shape != (n,):
            raise ValueError(f"visible must be ({n},); got {visible.shape}")
        if benefit.shape[1] < 1 and n:
            raise ValueError("every node needs at least one level (K ≥ 1)")
        ids = np.arange(n)
        if np.any(parent < -1) or np.any((parent >= 0) & (parent >= ids)):
            raise ValueError("parent ids must be −1 (root) or smaller than the child's id")
        if n and not valid[:, 0].all():
            raise ValueError("every node needs its coarsest level (valid[:, 0])")
        if n and np.any(valid[:, 1:] & ~valid[:, :-1]):
            raise ValueError("each node's valid levels must be a prefix 0 .. K_i − 1")
        has_parent = parent >= 0
        if np.any(visible[has_parent] & ~visible[parent[has_parent]]):
            raise ValueError("a visible node's parent must be visible (hierarchical culling)")
        return cls(parent, benefit, cost, valid, visible)

    @cached_property
    def children(self) -> tuple[np.ndarray, np.ndarray]:
        """Children as CSR: node i's children are ``ids[offsets[i]:offsets[i + 1]]``, ascending."""
        return _csr(self.parent, np.ones(self.n, bool), self.n)

    @cached_property
    def visible_children(self) -> tuple[np.ndarray, np.ndarray]:
        """Visible children as CSR (what a split replaces a node by)."""
        return _csr(self.parent, self.visible, self.n)

    @cached_property
    def visible_leaf(self) -> np.ndarray:
        """(N,) bool: visible nodes with no visible child — the objects a cut must represent."""
        offsets, _ = self.visible_children
        return self.visible & (np.diff(offsets) == 0)

    @cached_property
    def finest(self) -> np.ndarray:
        """(N,) int64: each node's finest level K_i − 1."""
        return self.valid.sum(axis=1).astype(np.int64) - 1


def _csr(parent: np.ndarray, keep: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    child = np.nonzero((parent >= 0) & keep)[0]
    order = np.argsort(parent[child], kind="stable")  # stable: children stay ascending
    counts = np.bincount(parent[child], minlength=n)
    offsets = np.zeros(n + 1, np.int64)
    np.cumsum(counts, out=offsets[1:])
    return offsets, child[order].astype(np.int64)


def coarsest_cut(forest: Forest) -> np.ndarray:
    """(N,) int64: the starting cut — every visible root at level 0, everything else −1."""
    level = np.full(forest.n, -1, np.int64)
    level[(forest.parent < 0) & forest.visible] = 0
    return level


def is_valid_cut(forest: Forest, level: np.ndarray) -> bool:
    """Whether ``level`` is a valid cut: every visible leaf has exactly one ancestor-or-self
    in the cut, no invisible node is in it, and every cut node's level is one it has.

    Vectorised by pointer jumping up the trees: one numpy pass per tree level.
    """
    level = np.asarray(level)
    n = forest.n
    if level.shape != (n,) or not np.issubdtype(level.dtype, np.integer):
        return False
    if np.any(level < -1) or np.any(level >= forest.k):
        return False
    cut = level >= 0
    if np.any(cut & ~forest.visible):
        return False
    if np.any(~forest.valid[np.nonzero(cut)[0], level[cut]]):
        return False
    covered = cut.astype(np.int64)  # cut ancestors-or-self, per node
    up = forest.parent.copy()
    alive = np.nonzero(up >= 0)[0]
    while alive.size:
        covered[alive] += cut[up[alive]]
        up[alive] = forest.parent[up[alive]]
        alive = alive[up[alive] >= 0]
    return bool(np.all(covered[forest.visible_leaf] == 1))


def _values(db: np.ndarray, dc: np.ndarray, usable: np.ndarray) -> np.ndarray:
    """Value = Δbenefit / Δcost of increments; +inf when it gains benefit for no cost, nan when unusable."""
    usable = usable & (db > 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        value = np.where(dc > 0, db / np.where(dc > 0, dc, 1.0), np.inf)
    return np.where(usable, value, np.nan)


def solve(
    forest: Forest,
    budget: float,
    *,
    limit: TimeLimit = NO_LIMIT,
    state: dict | None = None,
    split_from: str = "any",
    check_every: int = 64,
    **opts,
) -> Result:
    """Mason & Blake's greedy over all hierarchies at once: best-value increment first, within budget.

    forest : the visible hierarchies (``Forest``)
    budget : seconds
    limit  : checked every ``check_every`` heap pops; on expiry the current cut is returned
             (valid and feasible) with ``stats["stopped"] = "limit"``
    state  : unused (no memory across frames; accepted for the solver contract)
    split_from : "any" — a cut node may be split at whatever level it is drawn at
             (the split's value compares the children with that level); "finest" — only
             once its finest level is drawn (each node's own chain is exhausted first)
    Returns a ``Result`` whose ``level`` is (N,): the level drawn at each node of the cut, −1 elsewhere.
    stats: increments, splits, raises, skipped (increments that did not fit), cut (nodes),
    over_budget, stopped.

    Increments that do not fit are set aside; they come back only if a later increment lowers
    the cost (a split whose children cost less than the node).
    """
    if split_from not in ("any", "finest"):
        raise ValueError(f"split_from must be 'any' or 'finest'; got {split_from!r}")
    n, k = forest.n, forest.k
    benefit, cost, valid = forest.benefit, forest.cost, forest.valid
    level = coarsest_cut(forest)
    stats = {"increments": 0, "splits": 0, "raises": 0, "skipped": 0}
    if n == 0:
        stats.update(cut=0, over_budget=False, stopped="done")
        return Result(level=level, cost=0.0, benefit=0.0, stats=stats)

    # Every increment any node could offer, as (N, K) arrays indexed by the level it starts from.
    offsets, kids = forest.visible_children
    cb = np.where(valid, benefit, 0.0)
    cc = np.where(valid, cost, 0.0)
    nonroot = kids  # visible non-root nodes, grouped by parent
    child_b = np.bincount(forest.parent[nonroot], weights=cb[nonroot, 0], minlength=n)
    child_c = np.bincount(forest.parent[nonroot], weights=cc[nonroot, 0], minlength=n)
    has_kids = np.diff(offsets) > 0
    up_ok = np.zeros((n, k), bool)
    up_ok[:, :-1] = valid[:, 1:]
    up_db = np.zeros((n, k))
    up_dc = np.zeros((n, k))
    up_db[:, :-1] = cb[:, 1:] - cb[:, :-1]
    up_dc[:, :-1] = cc[:, 1:] - cc[:, :-1]
    split_ok = valid & has_kids[:, None]
    if split_from == "finest":
        split_ok &= np.arange(k)[None, :] == forest.finest[:, None]
    up_val = _values(up_db, up_dc, up_ok)
    split_val = _values(child_b[:, None] - cb, child_c[:, None] - cc, split_ok)
    # Single entries are read with ``.item`` at flat index node·K + level (Python floats, no numpy
    # scalars); converting whole tables to lists would cost more than the few increments read.
    up_val_l, up_dc_l = up_val.ravel().item, up_dc.ravel().item
    split_val_l, split_dc_l = split_val.ravel().item, (child_c[:, None] - cc).ravel().item
    off_l, kids_l = offsets.item, kids

    # Heap entries: (−value, node, kind, from_level); kind 0 raise, 1 split. Stale entries
    # (the node has moved since) are dropped when popped.
    cut_nodes = np.nonzero(level >= 0)[0]
    heap = []
    for table, kind in ((up_val, 0), (split_val, 1)):
        v = table[cut_nodes, 0]
        ok = ~np.isnan(v)
        heap.extend(zip((-v[ok]).tolist(), cut_nodes[ok].tolist(), [kind] * int(ok.sum()), [0] * int(ok.sum())))
    heapq.heapify(heap)

    lev = level.tolist()
    spent = float(cc[cut_nodes, 0].sum())
    room = budget + _SLACK * abs(budget)
    deferred: list = []
    pops = 0
    stopped = "done"
    while heap:
        if pops % check_every == 0 and limit.expired():
            stopped = "limit"
            break
        pops += 1
        entry = heapq.heappop(heap)
        _, node, kind, start = entry
        if lev[node] != start:
            continue  # stale: raised or split since
        dc = up_dc_l(node * k + start) if kind == 0 else split_dc_l(node * k + start)
        if dc > 0 and spent + dc > room:
            stats["skipped"] += 1
            deferred.append(entry)
            continue
        spent += dc
        stats["increments"] += 1
        if kind == 0:
            stats["raises"] += 1
            lev[node] = new = start + 1
            for kd, table in ((0, up_val_l), (1, split_val_l)):
                v = table(node * k + new)
                if v == v:  # not nan
                    heapq.heappush(heap, (-v, node, kd, new))
        else:
            stats["splits"] += 1
            lev[node] = -1
            for child in kids_l[off_l(node):off_l(node + 1)].tolist():
                lev[child] = 0
                for kd, table in ((0, up_val_l), (1, split_val_l)):
                    v = table(child * k)
                    if v == v:
                        heapq.heappush(heap, (-v, child, kd, 0))
        if dc < 0 and deferred:
            # The cost fell: increments set aside may fit now.
            for e in deferred:
                heapq.heappush(heap, e)
            deferred.clear()

    level = np.asarray(lev, np.int64)
    drawn = np.nonzero(level >= 0)[0]
    total_cost = float(cost[drawn, level[drawn]].sum())
    total_benefit = float(benefit[drawn, level[drawn]].sum())
    stats.update(
        cut=int(drawn.size),
        over_budget=bool(total_cost > budget + 1e-9 * abs(budget)),
        stopped=stopped,
    )
    return Result(level=level, cost=total_cost, benefit=total_benefit, stats=stats)

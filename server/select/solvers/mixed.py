"""Mixed discrete and continuous LOD selection (Zach, Mantler & Karner 2002).

Discrete objects offer representations (the options of a ``Candidates``);
smooth objects (point-splat vegetation groups) take a resolution x ∈ [0, 1].
Both share one budget T:

    max Σ benefit_d(r) + Σ benefit_c(x)   s.t.   Σ cost_d(r) + Σ cost_c(x) ≤ T

with the paper's smooth model benefit_c(x) = weight · x^power (power ½: the
paper's √x) and cost_c(x) = fixed + slope · x, the fixed part paid once the
object is drawn at all.

Each iteration compares slope_d, the value Δbenefit/Δcost of the best discrete
increment, with slope_c, the benefit per second of raising the resolutions, and
spends budget where it gains most. Raising a smooth object from "not drawn" to
its first resolution is itself an increment: it jumps to x* where
benefit/cost is highest (the tangent from the origin; x* = 0 without a fixed
cost), after which its marginal value continues smoothly from that value.

The continuous step is the paper's line search "to t_opt where
d b̃_c / d cost = slope_d": because the smooth benefits are separable the search
direction is taken as the diagonal-Newton one (x moves straight to the
resolution whose marginal value per second equals the target slope) rather than
the barrier gradient, which needs many tiny steps near x = 0 where √x is
infinitely steep. One iteration takes a band: the longest run of increments in
falling value v_1 ≥ … ≥ v_j that fits together with raising the resolutions to
marginal value v_j (found by bisection), so the loop stays vectorised and every
iteration ends feasible. When the budget binds mid-band the resolutions take
what is left at a common price. A final redistribution at equal continuous cost
puts the resolutions at the KKT point (equal marginal benefit per second).

Variable splitting (Appendix A): objects under a quadtree node share one
resolution while the bound on the benefit lost by tying them — all the node's
objects free at the same cost (unclamped Lagrange optimum) minus the tied
benefit, the paper's k·S²·√X·(1 − 1/√n) in general form — stays under a
threshold that shrinks by 4 per level; otherwise the node splits into its
children, which take the Lagrange split of the shared cost
(x_c ∝ (W_c/S_c)^{1/(1−power)}; the paper's X_i ∝ S_i⁴ for power ½ and W ∝ S²),
clipped at 1 so the cost never rises.
"""

from __future__ import annotations

import numpy as np

from . import mixed_gradient
from .candidates import NO_LIMIT, Candidates, TimeLimit
from .mixed_problem import Smooth, discrete_increments, mixed_result
from .result import Result

__all__ = ["solve"]

_TINY = 1e-300


class _Tree:
    """Ancestors of every smooth object, for Appendix A's variable splitting."""

    def __init__(self, m: int, parent: np.ndarray | None):
        if parent is None:
            self.depth = np.zeros(m, np.int64)
            self.anc = np.arange(m)[None, :]
            return
        parent = np.asarray(parent, np.int64)
        if parent.shape[0] < m:
            raise ValueError("quadtree must list a parent for every object (length ≥ m)")
        chain = [np.arange(m)]
        while True:
            up = np.where(chain[-1] >= 0, parent[np.maximum(chain[-1], 0)], -1)
            if (up < 0).all():
                break
            chain.append(up)
            if len(chain) > parent.shape[0] + 1:
                raise ValueError("quadtree has a cycle")
        path = np.stack(chain)  # path[h, i]: ancestor h steps up (−1 past the root)
        self.depth = (path >= 0).sum(0) - 1
        dmax = int(self.depth.max()) if m else 0
        d = np.arange(dmax + 1)[:, None]
        up = np.clip(self.depth[None, :] - d, 0, None)
        self.anc = path[up, np.arange(m)[None, :]]  # anc[d, i]: ancestor at depth d (the object past its depth)


def _aggregate(gnode, w, s, f, x, active):
    uniq, inv = np.unique(gnode, return_inverse=True)
    cnt = np.bincount(inv)
    W = np.bincount(inv, w)
    S = np.bincount(inv, s)
    F = np.bincount(inv, f)
    xg = np.bincount(inv, x) / cnt
    ag = np.bincount(inv, active.astype(np.float64)) == cnt  # drawn once all its objects are
    return inv, W, S, F, xg, ag


def _lagrange(wt, sl, grp, spend, ng, p):
    """Resolutions maximising Σ wt·y^p at cost Σ sl·y = spend per group (unclamped): y ∝ (wt/sl)^{1/(1−p)}."""
    with np.errstate(divide="ignore"):
        lr = (np.log(wt) - np.log(sl)) / (1 - p)
    gmax = np.full(ng, -np.inf)
    np.maximum.at(gmax, grp, lr)
    gmax = np.where(np.isfinite(gmax), gmax, 0.0)
    r = np.exp(lr - gmax[grp])
    denom = np.bincount(grp, sl * r, minlength=ng)
    kappa = np.where(denom > 0, spend / np.maximum(denom, _TINY), 0.0)
    return kappa[grp] * r


def _target(logc, p, price, lo):
    """Resolution whose marginal value per second p·W·x^{p−1}/S equals ``price`` (clipped to [lo, 1]).

    logc : log(p·W/S) per variable; price broadcasts against it.
    """
    with np.errstate(divide="ignore"):
        lx = (logc - np.log(np.maximum(price, 0.0))) / (1.0 - p)
    return np.clip(np.exp(np.minimum(lx, 0.0)), lo, 1.0)


def _price_for(logc, p, S, lo, spend, price_lo):
    """Price λ ≥ price_lo at which raising the variables from lo costs at most ``spend`` (bisection)."""
    lhi = float(np.max(logc + (p - 1.0) * np.log(np.maximum(lo, _TINY)))) + 1.0
    llo = float(np.log(price_lo)) if price_lo > 0 else float(np.min(logc)) - 1.0
    for _ in range(200):
        mid = 0.5 * (llo + lhi)
        if float(np.dot(S, _target(logc, p, np.exp(mid), lo) - lo)) > spend:
            llo = mid
        else:
            lhi = mid
        if lhi - llo < 1e-13:
            break
    return float(np.exp(lhi))


def solve(
    cand: Candidates,
    budget: float,
    *,
    smooth: Smooth | None = None,
    limit: TimeLimit = NO_LIMIT,
    state: dict | None = None,
    iterations: int = 10_000,
    band: int | None = None,
    split_eps: float | None = None,
    direction: str = "newton",
    **opts,
) -> Result:
    """Select discrete options and smooth resolutions sharing one budget (Zach, Mantler & Karner 2002).

    cand       : discrete objects (may have n = 0)
    budget     : seconds
    smooth     : the continuous objects (``Smooth.empty()`` for none)
    iterations : bound on the interleaved iterations
    band       : most increments per iteration (None: all that fit; small bands give finer
                 anytime steps)
    split_eps  : Appendix A's root threshold on benefit lost by a shared variable
                 (default 1e-3 × Σ weight); it shrinks by 4 per quadtree level
    state      : unused (no memory across frames yet); accepted for the solver contract
    direction  : "newton" (this module's band steps) or "barrier" (the paper's own barrier
                 gradient ascent, ``mixed_gradient``; each object its own variable)
    Every iteration ends feasible; ``limit.expired()`` is checked between them.
    Result.level: option per discrete object (−1 not drawn); Result.x: resolution per smooth object.
    """
    smooth = Smooth.empty() if smooth is None else smooth
    if direction == "barrier":
        return mixed_gradient.solve(cand, budget, smooth=smooth, limit=limit, iterations=iterations,
                                    **{k: v for k, v in opts.items() if k in ("barrier", "x_floor")})
    if direction != "newton":
        raise ValueError(f"direction must be 'newton' or 'barrier', not {direction!r}")
    budget = float(budget)
    n = cand.n
    m = smooth.m
    p = float(smooth.power)
    if not 0.0 < p < 1.0:
        raise ValueError("Smooth.power must lie in (0, 1)")
    w = np.asarray(smooth.weight, np.float64)
    s = np.asarray(smooth.slope, np.float64)
    f = np.asarray(smooth.fixed, np.float64)
    if m and (np.any(s <= 0) or np.any(w < 0) or np.any(f < 0)):
        raise ValueError("Smooth needs slope > 0, weight ≥ 0, fixed ≥ 0")
    tree = _Tree(m, smooth.quadtree)
    eps0 = float(split_eps) if split_eps is not None else 1e-3 * float(w.sum())

    obj, opt, dd_b, dd_c, dval, chain = discrete_increments(cand, max(budget, 0.0))
    h = obj.size
    live = np.ones(h, bool)
    taken = np.zeros(h, bool)
    spent_d = 0.0

    x = np.zeros(m)
    active = f == 0  # free to draw: starts at x = 0
    gdepth = np.zeros(m, np.int64)
    rows = np.arange(m)
    stats = {"iterations": 0, "splits": 0, "increments": 0, "activations": 0, "bands": 0, "raises": 0}
    stopped = "done"
    price = float("inf")

    def split() -> int:
        """Appendix A: split every shared variable whose bound on lost benefit is over its threshold."""
        nonlocal x, gdepth
        done = 0
        while True:
            inner = gdepth < tree.depth
            if not inner.any():
                return done
            gnode = tree.anc[gdepth, rows]
            inv, W, S, F, xg, ag = _aggregate(gnode, w, s, f, x, active)
            xstar = np.minimum(1.0, p * F / (S * (1 - p)))
            X = np.maximum(xg, xstar)
            child = tree.anc[np.minimum(gdepth + 1, tree.anc.shape[0] - 1), rows]
            cu, cinv = np.unique(np.where(inner, child, -1 - inv), return_inverse=True)
            Wc = np.bincount(cinv, w)
            Sc = np.bincount(cinv, s)
            cg = np.zeros(cu.size, np.int64)
            cg[cinv] = inv  # group of each child
            y = _lagrange(Wc, Sc, cg, S * X, W.size, p)
            # Bound on the benefit lost by tying: every object of the subtree free at the same cost
            # (not only the children, whose averages can agree while their objects differ).
            yo = _lagrange(w, s, inv, S * X, W.size, p)
            opt_b = np.minimum(np.bincount(inv, w * yo**p, minlength=W.size), W)
            loss = opt_b - W * X**p
            gdep = np.zeros(W.size, np.int64)
            gdep[inv] = gdepth
            ginner = np.zeros(W.size, bool)
            ginner[inv] = inner
            cut = ginner & (loss > eps0 / 4.0**gdep) & (X > 0)
            if not cut.any():
                return done
            moved = cut[inv]
            gdepth = gdepth + moved
            # Children take the Lagrange split of the shared cost; clipping at 1 only lowers it.
            x = np.where(moved & ag[inv], np.minimum(y[cinv], 1.0), x)
            done += int(cut.sum())

    while True:
        if limit.expired():
            stopped = "limit"
            break
        if stats["iterations"] >= iterations:
            stopped = "limit"
            stats["reason"] = "iterations"
            break
        stats["iterations"] += 1
        if m:
            stats["splits"] += split()
        gnode = tree.anc[gdepth, rows] if m else np.zeros(0, np.int64)
        inv, W, S, F, xg, ag = _aggregate(gnode, w, s, f, x, active)
        remaining = budget - spent_d - float(np.dot(F, ag) + np.dot(S, xg * ag))
        tol = 1e-12 * max(budget, _TINY)

        # Discrete increments that no longer fit never will: drop them and their objects' later steps.
        kill = live & (dd_c > remaining)
        if kill.any():
            minpos = np.full(max(n, 1), np.iinfo(np.int64).max)
            np.minimum.at(minpos, obj[kill], chain[kill])
            live &= chain < minpos[obj]
        # Activations (not drawn → x*) of smooth variables that fit.
        xstar = np.minimum(1.0, p * F / (S * (1 - p))) if W.size else np.zeros(0)
        a_cost = F + S * xstar
        a_ok = ~ag & (a_cost <= remaining) & (W > 0)
        a_idx = np.flatnonzero(a_ok)
        a_val = W[a_idx] * xstar[a_idx] ** p / np.maximum(a_cost[a_idx], _TINY)
        room = ag & (xg < 1.0) & (W > 0)
        if not live.any() and a_idx.size == 0 and not room.any() and remaining > tol:
            # Last resort: a variable whose x* does not fit draws the fraction the rest pays for.
            part = ~ag & (F < remaining) & (W > 0)
            if part.any():
                xp = np.where(part, (remaining - F) / S, 0.0)
                g = int(np.argmax(np.where(part, W * xp**p, -1.0)))
                xstar[g] = min(1.0, xp[g])
                a_cost[g] = F[g] + S[g] * xstar[g]
                a_idx = np.array([g])
                a_val = np.array([W[g] * xstar[g] ** p / a_cost[g]])

        cap = h + W.size if band is None else max(1, int(band))
        d_idx = np.flatnonzero(live)[:cap]
        vals = np.r_[dval[d_idx], a_val]
        kind = np.r_[np.zeros(d_idx.size, np.int64), np.ones(a_idx.size, np.int64)]
        ref = np.r_[d_idx, a_idx]
        srt = np.argsort(-vals, kind="stable")[:cap]
        vals, kind, ref = vals[srt], kind[srt], ref[srt]
        dcost = np.empty(ref.size)
        dcost[kind == 0] = dd_c[ref[kind == 0]]
        dcost[kind == 1] = a_cost[ref[kind == 1]]

        logc = np.log(np.maximum(p * W / S, _TINY)) if W.size else np.zeros(0)
        if not room.any() and ref.size == 0:
            break
        if ref.size == 0:
            # Only the smooth part is left: raise every resolution, to full detail if the budget allows.
            if remaining <= tol:
                break
            rl = np.flatnonzero(room)
            full = float(np.dot(S[rl], 1.0 - xg[rl]))
            lam = 0.0 if full <= remaining else _price_for(logc[rl], p, S[rl], xg[rl], remaining, 0.0)
            xg[rl] = _target(logc[rl], p, lam, xg[rl])
            price = min(price, lam)
            stats["raises"] += 1
        else:
            # The band: increments of falling value v_1 ≥ … ≥ v_B; at price v_j the smooth
            # variables (and those activated up to j) are raised so their marginal value is v_j.
            pos = np.full(W.size, np.iinfo(np.int64).max)  # band position where a variable joins
            pos[ag] = -1
            isact = kind == 1
            pos[ref[isact]] = np.flatnonzero(isact)
            sub = np.flatnonzero((pos < vals.size) & (W > 0))
            lo_s, pos_s, S_s, c_s = np.where(ag, xg, xstar)[sub], pos[sub], S[sub], logc[sub]
            spend = np.cumsum(dcost)

            def over(q: int) -> bool:
                """Do increments 0..q and the raise to price v_q overrun the budget?"""
                inc = pos_s <= q
                up = _target(c_s[inc], p, vals[q], lo_s[inc]) - lo_s[inc]
                return spend[q] + float(np.dot(S_s[inc], up)) > remaining + tol

            # Costs rise with q (more increments, lower price): bisect the longest prefix that fits.
            j = vals.size  # prefix length taken
            if over(vals.size - 1):
                a, b = 0, vals.size  # a prefix of length a fits, one of length b does not
                while b - a > 1:
                    mid = (a + b) // 2
                    if over(mid - 1):
                        b = mid
                    else:
                        a = mid
                j = a
            if j >= 1:
                tk = np.arange(j)
                dk = ref[tk[kind[tk] == 0]]
                ak = ref[tk[kind[tk] == 1]]
                taken[dk] = True
                live[dk] = False
                spent_d += float(dd_c[dk].sum())
                ag[ak] = True
                xg[ak] = xstar[ak]
                lam = float(vals[j - 1])
                sel = ag & (W > 0)
                xg[sel] = _target(logc[sel], p, lam, np.maximum(xg[sel], 0.0))
                price = min(price, lam)
                stats["increments"] += int(j)
                stats["activations"] += int(ak.size)
                stats["bands"] += 1
            else:
                # Raise and first increment do not fit together: slope_c beats slope_d, so raise
                # (to v_1, or as far as the budget allows); the increment is then dropped.
                if not room.any() or remaining <= tol:
                    # Nothing to raise and the increment cannot come with a raise: take it alone if it fits.
                    if dcost[0] <= remaining:
                        r0 = ref[0]
                        if kind[0] == 0:
                            taken[r0] = True
                            live[r0] = False
                            spent_d += float(dd_c[r0])
                        else:
                            ag[r0] = True
                            xg[r0] = xstar[r0]
                            stats["activations"] += 1
                        stats["increments"] += 1
                    else:
                        break
                else:
                    rl = np.flatnonzero(room)
                    need = float(np.dot(S[rl], _target(logc[rl], p, vals[0], xg[rl]) - xg[rl]))
                    lam = float(vals[0]) if need <= remaining else _price_for(
                        logc[rl], p, S[rl], xg[rl], remaining, float(vals[0]))
                    xg[rl] = _target(logc[rl], p, lam, xg[rl])
                    price = min(price, lam)
                    stats["raises"] += 1
        if m:
            x = xg[inv]
            active = ag[inv] | (f == 0)

    # Redistribution: at equal continuous cost, the common-price allocation is the KKT optimum.
    if m and active.any():
        gnode = tree.anc[gdepth, rows]
        inv, W, S, F, xg, ag = _aggregate(gnode, w, s, f, x, active)
        sel = np.flatnonzero(ag & (W > 0))
        if sel.size:
            spend = float(np.dot(S[sel], xg[sel]))
            logc = np.log(np.maximum(p * W[sel] / S[sel], _TINY))
            zero = np.zeros(sel.size)
            if float(S[sel].sum()) > spend:
                lam = _price_for(logc, p, S[sel], zero, spend, 0.0)
                xn = _target(logc, p, lam, zero)
                if float(np.dot(W[sel], xn**p)) > float(np.dot(W[sel], xg[sel] ** p)):
                    xg[sel] = xn
                    x = xg[inv]

    stats.update(stopped=stopped, price=price, variables=int(np.unique(tree.anc[gdepth, rows]).size) if m else 0)
    return mixed_result(cand, budget, (obj, opt, chain, taken), (w, s, f, p), x, active, stats)

"""The LOD methods the evaluation and the failure scenarios run, and what a session does with them
(``server/session.py``, ``server/select/selection.py``):

- ``none``, ``static``, ``feedback`` — F&S's baselines (``solvers/baselines.py``);
  ``none`` and ``static`` ignore the budget, so they run once, at the target.
- ``optimization`` — F&S's predictive incremental optimisation
  (``solvers/incremental.py``), over the flat view (mesh leaves).
- ``hierarchical`` — Mason & Blake / Zach's solver over the hierarchical view
  (HLOD and terrain trees; on a scene without hierarchies every object is a root).
- ``predictive`` — Zach 2002: the hierarchical solver, selecting for the
  *predicted* camera path with the conservative camera, and geomorphing
  between levels.
- ``mixed`` — Zach, Mantler & Karner 2002: meshes and terrain (the flat view, screen-space error accuracy) plus the
  continuous resolution of tree groups, predicted and morphed; only where the
  scene has tree groups.

``predict=False`` means the session selects for the client's latest reported
pose alone (``Session._interval``: one view, widened by ``margin_deg``) — what
F&S's frame-by-frame methods see; ``morph=False`` means a new selection takes
over at its switch time at once (no morph window τ before it, no morph maps).

The evaluation runs every budget-dependent method without and with the client's
frame governor (``hello.governor``, ``bench.evaluate.RunSpec.governor``).
"""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["Method", "METHODS"]


@dataclass(frozen=True)
class Method:
    """One method of the evaluation: the solver a session asks for, and how it asks.

    budget_dependent : False for methods that ignore the target (run once, at the target)
    continuous_only : run only on scenes with continuous objects (tree groups)
    """

    name: str
    solver: str
    predict: bool
    morph: bool
    budget_dependent: bool
    continuous_only: bool
    title: str


METHODS: dict[str, Method] = {m.name: m for m in (
    Method("none", "none", False, False, False, False, "None: every object at full detail (F&S)"),
    Method("static", "static", False, False, False, False, "Static: ≥ 1024 pixels per polygon (F&S)"),
    Method("feedback", "feedback", False, False, True, False,
           "Feedback: Static's threshold scaled by the last frame (F&S)"),
    Method("optimization", "optimization", False, False, True, False,
           "Optimization: incremental benefit/cost under the budget (F&S)"),
    Method("hierarchical", "hierarchical", False, False, True, False,
           "Hierarchical: increments over the HLOD forest (Mason & Blake, Zach)"),
    Method("predictive", "hierarchical", True, True, True, False,
           "Predictive: hierarchical + predicted path + geomorphing (Zach 2002)"),
    Method("mixed", "mixed", True, True, True, True,
           "Mixed: meshes and continuous tree groups, predicted and morphed (ZMK 2002)"),
)}


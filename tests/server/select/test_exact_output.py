"""The exact solver (HiGHS) writes nothing to standard output: not its banner, not its log.

HiGHS prints its banner to file descriptor 1 the first time a solver is used in a
process, so the check runs once in a fresh process (where the first solve is the
one that would print it) and once here under ``capfd``, which sees descriptor 1.
"""

from __future__ import annotations

import subprocess
import sys
import textwrap

import numpy as np

from server.select.solvers import exact
from server.select.solvers.candidates import Candidates

SOLVE = """
import numpy as np
from server.select.solvers import exact
from server.select.solvers.candidates import Candidates
cand = Candidates.of([[1.0, 1.5], [2.0, 2.2]], [[1.0, 3.0], [1.0, 2.0]])
r = exact.solve(cand, 3.0)
assert r.stats["stopped"] == "done", r.stats
"""


def test_an_exact_solve_in_a_fresh_process_writes_nothing_to_stdout():
    out = subprocess.run([sys.executable, "-c", textwrap.dedent(SOLVE)], capture_output=True, text=True,
                         timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout == ""


def test_an_exact_solve_writes_nothing_to_file_descriptor_one(capfd):
    rng = np.random.default_rng(0)
    cost = np.cumsum(rng.uniform(0.1, 1.0, (30, 3)), axis=1)
    benefit = np.cumsum(np.sort(rng.uniform(0.0, 1.0, (30, 3)), axis=1)[:, ::-1], axis=1)
    r = exact.solve(Candidates.of(benefit, cost), float(cost[:, 1].sum()))
    assert r.stats["stopped"] == "done"
    out, _ = capfd.readouterr()
    assert out == ""

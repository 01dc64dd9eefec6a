"""``piezod audit``: where the model and the measured stage disagree, why, and what a better model gains.

Pipeline: :mod:`~piezod.audit.data` (experiments, scans, segments) ->
:mod:`~piezod.audit.baseline` (thesis model (3.8) or hysteresis ODE (2.21)) ->
:mod:`~piezod.audit.candidates` (one physical extension per effect id) ->
:mod:`~piezod.audit.fitting` (joint least squares, held-out error) ->
:mod:`~piezod.audit.decide` (BIC + held-out gain, greedy forward selection) ->
:mod:`~piezod.audit.report` / :mod:`~piezod.audit.plots`.

:mod:`~piezod.audit.synthetic` generates thesis-model sessions with hidden effects for tests.
"""

from __future__ import annotations

from piezod.audit.candidates import EFFECTS
from piezod.audit.decide import AuditOptions, AuditResult, CandidateResult, run_audit
from piezod.audit.report import print_summary, result_json

#: Every ``cause`` the audit can name.
#: ``switching``, ``sensitivity_loss`` come from the model-free checks (:mod:`piezod.audit.outside`),
#: ``undetermined`` from :mod:`piezod.audit.degenerate`.
CAUSES: tuple[str, ...] = (
    "none",
    *EFFECTS,
    "switching",
    "sensitivity_loss",
    "sensitivity_gain",
    "undetermined",
    "unexplained",
)

__all__ = [
    "CAUSES",
    "EFFECTS",
    "AuditOptions",
    "AuditResult",
    "CandidateResult",
    "print_summary",
    "result_json",
    "run_audit",
]

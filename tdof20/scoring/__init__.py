"""The scoring layer: metrics (:mod:`tdof20.scoring.metrics`), scoring a results file against a
dataset's targets (:mod:`tdof20.scoring.scoring`) and the report (:mod:`tdof20.scoring.report`)."""

from tdof20.scoring.metrics import add, add_batch, adds, adds_batch, proj2d, proj2d_batch
from tdof20.scoring.scoring import Evaluation, evaluate, score, score_command

__all__ = ["Evaluation", "add", "add_batch", "adds", "adds_batch", "evaluate", "proj2d", "proj2d_batch", "score",
           "score_command"]

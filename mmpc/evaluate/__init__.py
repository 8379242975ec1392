"""Batch offline evaluation: drivers x scenarios x seeds, on this machine or a Ray cluster.

:func:`evaluate` plans the tasks (:mod:`~mmpc.evaluate.tasks`), runs them on a backend
(:mod:`~mmpc.evaluate.backends`: in this process, a process pool or Ray), keeps the rows in
the folder's files (:mod:`~mmpc.evaluate.store`) and writes the report
(:mod:`~mmpc.evaluate.report`). :func:`search_ceiling` (:mod:`~mmpc.evaluate.ceiling`) bounds
them: the best any driver could do on a seed, found by a search that knows the future.
"""

from mmpc.evaluate.backends import Backend, run_tasks
from mmpc.evaluate.ceiling import CeilingConfig, SeedCeiling, search_ceiling
from mmpc.evaluate.evaluation import Evaluation, evaluate
from mmpc.evaluate.report import format_table, paired_differences, summarize, write_report
from mmpc.evaluate.store import COLUMNS, METRIC_COLUMNS, EvaluationFolderError, read_episodes, scenario_fingerprint
from mmpc.evaluate.tasks import EvaluationConfig, GroupTask, run_group

__all__ = [
    "COLUMNS", "METRIC_COLUMNS", "Backend", "CeilingConfig", "Evaluation", "EvaluationConfig", "EvaluationFolderError", "GroupTask",
    "evaluate", "format_table", "paired_differences", "read_episodes", "run_group", "run_tasks", "scenario_fingerprint", "search_ceiling", "SeedCeiling", "summarize",
    "write_report",
]

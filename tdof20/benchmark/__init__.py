"""Benchmark stage: dataset splits, scoring of submitted results, reports."""

from tdof20.benchmark.metrics import add, add_batch, adds, adds_batch, proj2d, proj2d_batch
from tdof20.benchmark.report import report_markdown, report_text, table_markdown, table_text, write_plots
from tdof20.benchmark.results import HEADER, Results, read_results, write_results_csv
from tdof20.benchmark.scoring import Evaluation, evaluate, score, score_command

"""Experiments: the paper's tables (:mod:`tdof20.experiments.reproduce`,
:mod:`tdof20.experiments.tables`) and the demo (:mod:`tdof20.experiments.demo`). They use every
layer below; nothing imports them but the command line."""

"""The dataset layer: layouts and their readers (:mod:`tdof20.dataset.reader`), building a dataset
from annotated scenes (:mod:`tdof20.dataset.build`), the protocols' splits and validation parts
(:mod:`tdof20.dataset.splits`, :mod:`tdof20.dataset.validation`), scene naming
(:mod:`tdof20.dataset.naming`), the TDoF20 release importer (:mod:`tdof20.dataset.importer`) and
the results format (:mod:`tdof20.dataset.results`). It imports geometry, formats and objects only."""

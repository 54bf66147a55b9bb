"""The dataset layer: layouts, one reader class each behind one interface
(:mod:`tdof20.dataset.layouts`; :mod:`tdof20.dataset.reader` re-exports its names), building a
dataset from annotated scenes (:mod:`tdof20.dataset.scene_input` checks them,
:mod:`tdof20.dataset.build` writes tdof20's layout, :mod:`tdof20.dataset.build_bop` BOP's), a built
dataset's parts, counts and shards (:mod:`tdof20.dataset.stats`, :mod:`tdof20.dataset.shards`), the
protocols' splits and validation parts (:mod:`tdof20.dataset.splits`, :mod:`tdof20.dataset.validation`),
scene naming (:mod:`tdof20.dataset.naming`), the TDoF20 release importer (:mod:`tdof20.dataset.importer`)
and the results format (:mod:`tdof20.dataset.results`). It imports geometry, formats and objects only."""

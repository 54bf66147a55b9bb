"""The benchmark server (docs/server.md): researchers download a public release of a dataset
(:mod:`~tdof20.server.publish`), submit results through pages, a command or plain HTTP
(:mod:`~tdof20.server.app`, :mod:`~tdof20.server.client`); a submission is checked at once with the
results reader's strict checks, stored durably, queued (:mod:`~tdof20.server.db`) and scored by
worker processes (:mod:`~tdof20.server.worker`) with the scoring package's own scorer. Accounts
and tokens: :mod:`~tdof20.server.auth`; the file store: :mod:`~tdof20.server.store`; what of the
dataset the server may tell: :mod:`~tdof20.server.facts`."""

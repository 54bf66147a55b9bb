"""Review and correct an annotated scene in a local web app (``tdof20 annotate review SCENE``).

:func:`review_command` serves :func:`make_app`'s app (FastAPI, Jinja2 pages, three.js shipped in
``static/``); :class:`~tdof20.review.scene.ReviewScene` holds the scene and makes the corrections,
each an entry of the scene's journal ``work/corrections.jsonl``
(:mod:`tdof20.annotate.corrections`), which the place and label stages honour. A pose a person
gives passes the pipeline's own gates first (:mod:`tdof20.review.gates`); relabel runs in a child
process group that dies with the app (:mod:`tdof20.review.relabel`). See docs/annotate.md,
"Reviewing and correcting a scene".
"""

from tdof20.review.app import make_app, review_command
from tdof20.review.scene import ReviewScene

__all__ = ["ReviewScene", "make_app", "review_command"]

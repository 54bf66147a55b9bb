"""Annotation: from a raw capture session to a labelled BOP scene (stages).

    from tdof20.annotate import annotate, AnnotateConfig
    summary = annotate("sessions/m08", "scenes/m08", models_dir="models/")

The stages' modules: :mod:`~tdof20.annotate.registration` (register), :mod:`~tdof20.annotate.reconstruct`
(reconstruct), :mod:`~tdof20.annotate.models` and :mod:`~tdof20.annotate.modelbuild` (model, place),
:mod:`~tdof20.annotate.label` (label), :mod:`~tdof20.annotate.qa` and :mod:`~tdof20.annotate.evaluate`
(qa); :mod:`~tdof20.annotate.pipeline` runs them in order, resumably. Names other than the
registration's are imported on first use, so ``import tdof20.annotate`` stays light.
"""

from __future__ import annotations

import importlib
from typing import Any

from tdof20.annotate.registration import (
    ArmRegistration,
    FrameRegistration,
    RegistrationConfig,
    RegistrationResult,
    evaluate_against_truth,
    register_session,
    truth_T_ref_frame,
)

_LAZY = {
    # the pipeline
    "STAGES": "pipeline", "AnnotateConfig": "pipeline", "PlaceConfig": "pipeline", "QAConfig": "pipeline",
    "annotate": "pipeline", "load_annotate_config": "pipeline", "annotate_config_from_dict": "pipeline",
    "parse_stages": "pipeline", "summary_text": "pipeline",
    # the stages
    "ReconstructionConfig": "reconstruct", "Reconstruction": "reconstruct",
    "ModelFitConfig": "models", "ModelFit": "models", "fit_model": "models",
    "ModelBuildConfig": "modelbuild", "BuiltModel": "modelbuild", "build_model_from_cluster": "modelbuild",
    "write_models": "modelbuild", "load_models": "modelbuild",
    "LabelConfig": "label", "label_scene": "label",
    "write_qa": "qa",
    "evaluate_scene": "evaluate", "evaluate_command": "evaluate",
}

__all__ = ["ArmRegistration", "FrameRegistration", "RegistrationConfig", "RegistrationResult",
           "evaluate_against_truth", "register_session", "truth_T_ref_frame", *_LAZY]


def __getattr__(name: str) -> Any:
    mod = _LAZY.get(name)
    if mod is None:
        raise AttributeError(f"module 'tdof20.annotate' has no attribute {name!r}")
    value = getattr(importlib.import_module(f"tdof20.annotate.{mod}"), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY))

"""Annotation: from a raw capture session to a labelled BOP scene (stages).

    from tdof20.annotate import annotate, AnnotateConfig
    summary = annotate("sessions/m08", "scenes/m08", models_dir="models/")

The stages' rooms: :mod:`~tdof20.annotate.registration` with :mod:`~tdof20.annotate.turntable` and
:mod:`~tdof20.annotate.icp` (register), :mod:`~tdof20.annotate.reconstruct` with
:mod:`~tdof20.annotate.fusion` (reconstruct), :mod:`~tdof20.annotate.place`,
:mod:`~tdof20.annotate.models` and :mod:`~tdof20.annotate.modelbuild` (model, place),
:mod:`~tdof20.annotate.label` (label), :mod:`~tdof20.annotate.qa` and :mod:`~tdof20.annotate.evaluate`
(qa). :mod:`~tdof20.annotate.stages` describes each stage once (a record: name, needs, run,
inputs, outputs); :mod:`~tdof20.annotate.pipeline` walks them in order, resumably, with the
scene folder's state and lock (:mod:`~tdof20.annotate.state`) and the options
(:mod:`~tdof20.annotate.config`). Names other than the registration's options and results are
imported on first use, so ``import tdof20.annotate`` stays light (no open3d).
"""
from __future__ import annotations

import importlib
from typing import Any

from tdof20.annotate.registration_config import RegistrationConfig
from tdof20.annotate.registration_result import ArmRegistration, FrameRegistration, RegistrationResult

_LAZY = {
    "register_session": "registration",
    # the pipeline: options, stages, orchestrator
    "AnnotateConfig": "config", "PlaceConfig": "config", "QAConfig": "config",
    "load_annotate_config": "config", "annotate_config_from_dict": "config",
    "STAGES": "stages", "parse_stages": "stages",
    "annotate": "pipeline", "summary_text": "pipeline",
    # the stages
    "ReconstructionConfig": "reconstruct", "Reconstruction": "reconstruct",
    "ModelFitConfig": "models", "ModelFit": "models", "fit_model": "models",
    "ModelBuildConfig": "modelbuild_config", "BuiltModel": "modelbuild", "build_model_from_cluster": "modelbuild",
    "write_models": "modelbuild", "load_models": "modelbuild",
    "LabelConfig": "label", "label_scene": "label",
    "write_qa": "qa",
    "evaluate_scene": "evaluate", "evaluate_command": "evaluate",
    "evaluate_against_truth": "evaluate", "truth_T_ref_frame": "evaluate", "truth_label_inputs": "evaluate",
}

__all__ = ["ArmRegistration", "FrameRegistration", "RegistrationConfig", "RegistrationResult", *_LAZY]


def __getattr__(name: str) -> Any:
    mod = _LAZY.get(name)
    if mod is None:
        raise AttributeError(f"module 'tdof20.annotate' has no attribute {name!r}")
    value = getattr(importlib.import_module(f"tdof20.annotate.{mod}"), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY))
